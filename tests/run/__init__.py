"""A run's folder (run/folder.py), how it begins and resumes (run/start.py, run/scene.py) and stops (stopping.py)."""
