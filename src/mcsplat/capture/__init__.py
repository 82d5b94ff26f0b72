"""`mcsplat process`: photos or a video to a scene folder (SCENE/images + SCENE/sparse/0, PINHOLE) with pycolmap.

frames.py gathers the input (a folder of photos, or the sharpest frames of a video), sfm.py runs feature extraction,
matching and incremental mapping in worker.py's child process (child.py starts, watches and stops it), process.py
orchestrates them, undistorts the best model and moves the finished scene into place in one rename. registration.py
says which photos SfM left out and why (in the worker, from the features' database and the models).
"""

from .process import ProcessOptions, ProcessSummary, process

__all__ = ["ProcessOptions", "ProcessSummary", "process"]
