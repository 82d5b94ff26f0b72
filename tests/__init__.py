"""The package's tests, in folders that mirror src/mcsplat/: a package's tests in the folder of its name, the top-level
modules' in training/ (the method and the step), run/ (a run's folder, resume, stopping) and docs/ (the docs and the
layering). Shared fixtures are in conftest.py here; support/ holds the helpers tests import."""
