# Two commands do all the set-up on a fresh machine: `make demo` and `make test`. Both are idempotent.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
APT_PACKAGES := libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libegl-mesa0 libgl1-mesa-dri libtk8.6 xvfb xdotool
TORCH := torch==2.13.0
STAMP := $(VENV)/.kpd-installed

.PHONY: demo test bench system venv clean

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
	$(PIP) install -q -e '.[train,dev]'
	touch $(STAMP)

venv: system $(STAMP)

demo: venv
	$(VENV)/bin/kpd demo --out demo-output --force

test: venv
	$(PY) -m pytest -n 2 -q
	$(VENV)/bin/lint-imports

bench: venv
	@mkdir -p benchmarks/results; for b in benchmarks/bench_*.py; do n=$$(basename $$b .py); n=$${n#bench_}; \
	  echo "== $$b -> benchmarks/results/$$n.json"; $(PY) $$b > benchmarks/results/$$n.json.tmp && mv benchmarks/results/$$n.json.tmp benchmarks/results/$$n.json; done

clean:
	rm -rf $(VENV) demo-output .pytest_cache .hypothesis build *.egg-info
