# Two commands do all the set-up on a fresh machine: `make demo` and `make test`. Both are idempotent.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
APT_PACKAGES := libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libegl-mesa0 libgl1-mesa-dri libtk8.6 xvfb xdotool chromium chromium-driver
TORCH := torch==2.13.0
STAMP := $(VENV)/.kpd-installed
# Blender as a Python module (bpy 4.2 LTS, for Python 3.11) in a venv of its own: the glTF rig tests import kpd's
# files with Blender's own importer. npm installs three.js (the browser editor) and the Khronos glTF Validator from
# package-lock.json; the files of three.js the page loads are copied into the package (viewer/web/vendor).
BLENDER_VENV := .venv-blender
BLENDER_STAMP := $(BLENDER_VENV)/.kpd-installed
BPY := bpy==4.2.23
WEB_STAMP := viewer/web/vendor/.kpd-installed
THREE_FILES := LICENSE build/three.module.js build/three.core.js examples/jsm/loaders/GLTFLoader.js \
	examples/jsm/utils/BufferGeometryUtils.js examples/jsm/utils/SkeletonUtils.js examples/jsm/controls/OrbitControls.js

.PHONY: demo test docs bench dist system venv web blender clean

# System packages: installed when missing and we are root (open3d needs libusb; rendering needs vulkan/mesa, and
# EGL + Mesa GL for the OpenGL pictures; the editor's panel needs Tk;
# the editor's tests need xvfb and xdotool).
system:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then echo "installing system packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	  else echo "missing system packages (run as root or install them):$$missing" >&2; fi; fi

$(PY):
	python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip

# torch first, at the exact version that this machine has as a CPU build; then the project with its extras.
$(STAMP): pyproject.toml | $(PY)
	$(PIP) install -q $(TORCH)
	$(PIP) install -q -e '.[train,dev,cluster]'
	touch $(STAMP)

# The package's bytecode compiled, as pip does when it installs a wheel: an editable install leaves it to the first
# import, which does not write it where PYTHONDONTWRITEBYTECODE is set (as on CI): 0.2 s of every command's start.
venv: system $(STAMP)
	$(PY) -m compileall -q kpd viewer export >/dev/null

$(WEB_STAMP): package.json package-lock.json
	npm ci --no-audit --no-fund --loglevel=error
	rm -rf viewer/web/vendor/three
	for f in $(THREE_FILES); do mkdir -p viewer/web/vendor/three/$$(dirname $$f) && \
	  cp node_modules/three/$$f viewer/web/vendor/three/$$f; done
	touch $(WEB_STAMP)

web: $(WEB_STAMP)

$(BLENDER_STAMP):
	python3 -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/pip install -q --upgrade pip
	$(BLENDER_VENV)/bin/pip install -q $(BPY)
	touch $(BLENDER_STAMP)

blender: $(BLENDER_STAMP)

demo: venv
	$(VENV)/bin/kpd demo --out demo-output --force

test: venv web blender
	$(PY) -m pytest -n 2 -q
	$(VENV)/bin/lint-imports
	$(VENV)/bin/ruff check kpd viewer export tests benchmarks docs/conf.py docs/pictures.py

# The documentation: docs/*.md and the API reference from the docstrings, into docs/_build/html; any Sphinx warning
# fails the build. The per-module pages are generated afresh (docs/api/_generated), so a moved module leaves none.
docs: venv
	rm -rf docs/api/_generated
	$(VENV)/bin/sphinx-build -W --keep-going -q -b html docs docs/_build/html

bench: venv web blender
	@mkdir -p benchmarks/results; for b in benchmarks/bench_*.py; do n=$$(basename $$b .py); n=$${n#bench_}; \
	  echo "== $$b -> benchmarks/results/$$n.json"; $(PY) $$b > benchmarks/results/$$n.json.tmp && mv benchmarks/results/$$n.json.tmp benchmarks/results/$$n.json; done

# The release, into dist/: the sdist, then the wheel built from that sdist (python -m build, as pip builds a wheel
# from an sdist: a file the sdist lacks is missing from the wheel too), each with the shipped bundles, the browser page
# and the three.js files that make web takes from the npm lock (never committed).
dist: venv web
	rm -f dist/kpd-*.tar.gz dist/kpd-*.whl
	$(PY) -m build --outdir dist .

clean:
	rm -rf $(VENV) $(BLENDER_VENV) node_modules viewer/web/vendor demo-output docs/_build docs/api/_generated .pytest_cache .hypothesis build dist *.egg-info
