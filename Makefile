# BlendSR developer entry points. Everything installs into ./.venv.
PY ?= python3.11
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-stamp
export MALLOC_MMAP_THRESHOLD_ := 4294967296
export MALLOC_TRIM_THRESHOLD_ := 68719476736

.PHONY: setup test demo addon bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml Makefile
	@test -x $(VPY) || $(PY) -m venv $(VENV)
	$(VPY) -m pip install --quiet --upgrade pip
	# torch first, pinned to the CPU wheel present on this project's machines; the rest keep ranges it satisfies.
	$(VPY) -m pip install --quiet "torch==2.13.0"
	$(VPY) -m pip install --quiet -e ".[dev]"
	@touch $(STAMP)

test: setup
	$(VPY) -m pytest -n 2 --timeout 900 -q

demo: setup
	$(VPY) -m gbuffer_export.cli demo -o demo_out

addon: setup
	$(VPY) -m blender_addon.build -o dist

bench: setup
	$(VPY) -m gbuffer_export.cli bench render

clean:
	rm -rf $(VENV) demo_out dist
