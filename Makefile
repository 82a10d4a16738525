# Two commands for users: `make demo` and `make test` (see README). Everything else is a building block.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
CSRC := $(shell find csrc -name '*.cpp' -o -name '*.h')
DEPS_STAMP := $(VENV)/.deps-stamp
BUILD_STAMP := .build-stamp
PYTEST_ARGS ?=
DEMO_ARGS ?=

.PHONY: demo demo-object render-demo test build bench bench-peer clean venv gpu-check gpu-wheels

$(PY):
	python3 -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip setuptools wheel

# torch first (setup.py needs it), then the package's own dependencies from setup.cfg.
$(DEPS_STAMP): setup.cfg setup.py | $(PY)
	$(PIP) install --quiet torch numpy ninja
	TA_SKIP_EXT=1 $(PIP) install --quiet --no-build-isolation -e '.[test]'
	touch $@

venv: $(DEPS_STAMP)

# Ahead-of-time build of torch_appearance._C; rebuilt whenever a C++ source changes.
$(BUILD_STAMP): $(DEPS_STAMP) $(CSRC) setup.py torch_appearance/_buildinfo.py
	$(PY) setup.py --quiet build_ext --inplace
	touch $@

build: $(BUILD_STAMP)

# The main job on a built-in default: a small print optimisation of the ColorChecker slab (a few minutes).
demo: build
	rm -rf results/demo
	$(VENV)/bin/ta-optimize-print --target colorchecker $(DEMO_ARGS) --out results/demo

# The object job: a short print optimisation of the textured Spot model (public domain, in tests/data), with the
# naive and 2.5D remapped baselines and camera renders of the quantised print (a few minutes on 2 cores).
demo-object: build
	rm -rf results/demo-object
	$(VENV)/bin/ta-optimize-print --mesh tests/data/meshes/spot/spot_triangulated.obj \
		--texture tests/data/meshes/spot/spot_texture.png --height-mm 8 --dpi 150 --shell-mm 1.5 --spp 8 \
		--iterations 60 --eval-every 10 --eval-spp 64 --table-steps 4 --remap-baseline $(DEMO_ARGS) \
		--out results/demo-object

# The tracer alone: renders the built-in ink slab (PNG + EXR + timings).
render-demo: build
	$(PY) scripts/examples/demo.py --out results/render-demo

test: build
	$(PY) -m pytest -n 2 --dist loadfile $(PYTEST_ARGS)

bench: build
	$(PY) scripts/bench/bench_volpath.py

# Side by side with Mitsuba 3 (optional peer, never needed by the tests): its CPU backend needs Debian's libLLVM-15.
bench-peer: build
	$(PIP) install --quiet mitsuba==3.5.2 drjit==0.4.6
	@ldconfig -p | grep -q 'libLLVM-15.so' || (apt-get update -q && apt-get install -y -q libllvm15)
	DRJIT_LIBLLVM_PATH=$$(ldconfig -p | awk '/libLLVM-15.so/ {print $$NF; exit}') $(PY) scripts/bench/bench_peer.py

# The prepared check of the CUDA path (issue 47) for a lent GPU machine, in one call: builds the extension with that
# machine's own python3 and torch (its pins are not the project's), then runs scripts/bench/gpu_check.py (about 5
# minutes with the build on 16 cores; the JSON lands in $$OUT). The package imports kornia and OpenEXR, which that
# machine lacks: `make gpu-wheels` here puts their wheels in .whl/ (git-ignored); carry .whl with the call.
GPU_PY ?= python3
GPU_SITE ?= /tmp/ta-site
GPU_CHECK_ARGS ?=
gpu-check:
	if ls .whl/*.whl >/dev/null 2>&1; then $(GPU_PY) -m pip install -q --no-index --no-deps --no-compile \
		--no-cache-dir --upgrade --target $(GPU_SITE) .whl/*.whl; fi
	PYTHONPATH=$(GPU_SITE) $(GPU_PY) setup.py --quiet build_ext --inplace
	PYTHONUNBUFFERED=1 PYTHONPATH=$(CURDIR):$(GPU_SITE) $(GPU_PY) scripts/bench/gpu_check.py $(GPU_CHECK_ARGS)

gpu-wheels:
	f=$$(git rev-parse --git-path info/exclude); grep -qx '/.whl/' $$f 2>/dev/null || echo /.whl/ >> $$f
	$(PY) -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
		--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
		-d .whl kornia==0.9.0 kornia_rs==0.2.0 OpenEXR==3.5.3

clean:
	rm -rf build $(BUILD_STAMP) torch_appearance/_C*.so results
