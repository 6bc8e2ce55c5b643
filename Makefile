# Two commands a new user needs (see README):  make repro   and   make test
# Both set everything up first (idempotent): a virtual environment in .venv and the G1 model.

PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# lerobot's dataset reader, for the test that loads our datasets with it. Its releases pin
# torch<2.12, so it goes in with --no-deps plus only what `lerobot.datasets` imports (pinned).
LEROBOT_READER := lerobot==0.4.4 datasets==4.8.5 huggingface_hub==0.35.3 accelerate==1.15.0 \
                  pandas==3.1.1 multiprocess==0.70.19 dill==0.4.1 xxhash==4.1.0 httpx==0.28.1
# The Unitree SDK 2's message types for `adamimic deploy`. It pins cyclonedds==0.10.2, on PyPI only as
# source that needs the Cyclone DDS C library to build; its types run on the cyclonedds wheel pinned in
# pyproject.toml (tests/test_deploy.py), so it goes in with --no-deps.
UNITREE_SDK := unitree-sdk2==1.0.1

.PHONY: setup repro test bench clean-venv

$(STAMP): pyproject.toml Makefile
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test,warp]"
	$(PY) -m pipeline.robot.assets
	$(PY) -m pip install --quiet --no-deps $(LEROBOT_READER)
	$(PY) -m pip install --quiet --no-deps $(UNITREE_SDK)
	$(PY) -m pipeline.motion.importers --fetch-test-clips
	@touch $(STAMP)

setup: $(STAMP)

repro: setup
	. $(VENV)/bin/activate && python -m pipeline.config params.yaml && dvc repro

test: setup
	$(PY) -m pytest -q

bench: setup
	for b in benchmarks/*.py; do \
	  case $$b in *_gpu.py) $(PY) -c 'import sys, torch; sys.exit(not torch.cuda.is_available())' \
	    || { echo "skip $$b: needs a CUDA GPU"; continue; };; esac; \
	  $(PY) $$b || exit 1; done

clean-venv:
	rm -rf $(VENV)

# --- human video import (optional extra) ----------------------------------------------------
# mediapipe 0.10.21 needs numpy<2 and protobuf<5, so it lives in its own venv, called by
# pipeline/human/video.py as a subprocess. Pins are what pip resolved for it on Python 3.11.
VIDEO_VENV  := .venv-video
VIDEO_STAMP := $(VIDEO_VENV)/.installed
VIDEO_PKGS  := mediapipe==0.10.21 numpy==1.26.4 protobuf==4.25.9 opencv-contrib-python==4.11.0.86
# A real clip nobody here made: vtest.avi (pedestrians) from Debian's opencv-doc, no root needed.
VTEST       := .cache/video/vtest.avi

.PHONY: video-venv test-video-data

$(VIDEO_STAMP):
	@test -x $(VIDEO_VENV)/bin/python || $(PYTHON) -m venv $(VIDEO_VENV)
	$(VIDEO_VENV)/bin/python -m pip install --quiet $(VIDEO_PKGS)
	@touch $(VIDEO_STAMP)

video-venv: $(VIDEO_STAMP)

$(VTEST):
	mkdir -p $(dir $(VTEST))
	cd $(dir $(VTEST)) && { { apt-get download opencv-doc >/dev/null 2>&1 || { apt-get update -qq && apt-get download opencv-doc >/dev/null; }; } && \
	  dpkg-deb --fsys-tarfile opencv-doc_*.deb | tar -xO ./usr/share/doc/opencv-doc/examples/data/vtest.avi > vtest.avi.part && \
	  mv vtest.avi.part vtest.avi; status=$$?; rm -f opencv-doc_*.deb vtest.avi.part; exit $$status; }

# Best effort: without them the video test is skipped (with the reason), the rest still runs.
test-video-data:
	-@$(MAKE) --no-print-directory $(VIDEO_STAMP) $(VTEST)

test: test-video-data
