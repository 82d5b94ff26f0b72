"""A run's folder (run_dir.py), how it begins and resumes (run_start.py, run_scene.py) and stops (stopping.py)."""
