"""The outputs a render gives only when asked, computed around the compositing stage: the median depth (median.py),
the normal map and planar depth (normals.py), 2DGS's depth distortion (distortion.py); each a pass registered in
passes.py, run when a caller names its output (render(outputs={"normals"}))."""
