# Two commands a new user needs (see README):  make repro   and   make test
# Both set everything up first (idempotent): a virtual environment in .venv and the G1 model.

PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup repro test bench clean-venv

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test,warp]"
	$(PY) -m pipeline.robot.assets
	@touch $(STAMP)

setup: $(STAMP)

repro: setup
	. $(VENV)/bin/activate && dvc repro

test: setup
	$(PY) -m pytest -q

bench: setup
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

clean-venv:
	rm -rf $(VENV)
