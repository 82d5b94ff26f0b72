"""A training run's life outside the step: how it begins in its folder (start.py, setup.py), what it carries from step
to step and keeps in a checkpoint (state.py), what it tells its consumers (events.py), how it is scored
(evaluation.py) and recorded (metrics.py), the folder's layout (folder.py), the scene it trains on (scene.py), and a
trained run read back (trained.py)."""
