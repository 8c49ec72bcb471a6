# BlendSR developer entry points. Everything installs into ./.venv (Python 3.11).
PY ?= python3.11
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-stamp
# glibc page-faults every tensor above 32 MB without these (see docs): +25..80% time in torch.
export MALLOC_MMAP_THRESHOLD_ := 4294967296
export MALLOC_TRIM_THRESHOLD_ := 68719476736

.PHONY: setup test demo addon bench clean

setup: $(STAMP)

# Re-runs only when pyproject.toml or this Makefile changed; otherwise 'make setup' is a no-op.
$(STAMP): pyproject.toml Makefile
	@test -x $(VPY) || $(PY) -m venv $(VENV)
	$(VPY) -m pip install --quiet --disable-pip-version-check --upgrade pip
	# torch first, pinned to the CPU wheel; blendsr's own range (torch>=2.5) is then already satisfied.
	$(VPY) -m pip install --quiet --disable-pip-version-check "torch==2.13.0"
	$(VPY) -m pip install --quiet --disable-pip-version-check -e ".[dev]"
	@touch $(STAMP)

test: setup
	$(VPY) -m pytest -q -n 2 --timeout 1200 --durations=15

demo: setup
	$(VPY) -m gbuffer_export.cli demo -o demo_out

addon: setup
	$(VPY) -m blender_addon.build -o dist

bench: setup
	$(VPY) -m gbuffer_export.cli bench render

clean:
	rm -rf $(VENV) demo_out dist
