# image2sim: `make demo` and `make test` do all set-up on a fresh machine (see README).
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.image2sim-installed
# open3d needs libusb; CPU rendering needs OSMesa; ffmpeg decodes and encodes video.
APT_PACKAGES := libusb-1.0-0 libosmesa6 libgl1 libegl1 libgomp1 ffmpeg
export MUJOCO_GL ?= osmesa
export PYOPENGL_PLATFORM ?= osmesa

.PHONY: install demo test lint typecheck pytest samples benchmarks clean

install: $(STAMP)

$(STAMP): pyproject.toml Makefile constraints.txt
	@bash .ci/system-packages.sh $(APT_PACKAGES)
	@test -x $(PY) || python3 -m venv $(VENV)
	@# torch==2.13.0 first (the CPU build on this machine), then the project at the versions in constraints.txt;
	@# with uv where it can be had (a minute against pip's two and a half on a clean clone), else pip.
	bash .ci/python-packages.sh $(VENV)
	@touch $(STAMP)

demo: install
	$(VENV)/bin/image2sim ground samples/tabletop/video.mp4 -o out/demo/scene --aruco-size 0.12 --overwrite
	@echo "MuJoCo scene: out/demo/scene/scene.xml (manifest scene.json, picture preview.png)"

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

typecheck: install
	$(VENV)/bin/mypy

# Tests run in parallel, one worker per core (at most 4), a test file to a worker (its module fixtures are built
# once); a grounding two files share is built once per run (tests/conftest.py). PYTEST_WORKERS=0: no workers.
PYTEST_WORKERS ?= auto
PYTEST := $(PY) -m pytest -n $(PYTEST_WORKERS) --maxprocesses 4 --dist loadfile --no-loadscope-reorder
pytest: install
	$(PYTEST)

# mypy (a minute on one core from a cold cache) checks beside pytest rather than before it; its report follows
# pytest's, and either failing fails the target.
test: lint
	@log=$$(mktemp); $(VENV)/bin/mypy > $$log 2>&1 & mypy_pid=$$!; \
	$(PYTEST); pytest_rc=$$?; \
	wait $$mypy_pid; mypy_rc=$$?; echo "mypy:"; cat $$log; rm -f $$log; \
	test $$pytest_rc -eq 0 -a $$mypy_rc -eq 0

samples: install
	$(PY) samples/make_tabletop.py
	$(PY) samples/make_toss.py
	$(PY) samples/make_toss_occluded.py
	$(PY) samples/make_toss_moving.py
	$(PY) samples/make_tabletop.py --object-markers --out samples/tabletop_markers
	$(PY) samples/make_toss_markers.py

benchmarks: install
	$(PY) benchmarks/reconstruct.py
	$(PY) benchmarks/ground.py
	$(PY) benchmarks/collision.py
	$(PY) benchmarks/cube_toss.py
	$(PY) benchmarks/calibrate_throughput.py
	$(PY) benchmarks/diagnose.py
	$(PY) benchmarks/residual.py
	$(PY) benchmarks/residual_step_time.py
	$(PY) benchmarks/track.py

clean:
	rm -rf out .pytest_cache .mypy_cache .ruff_cache
