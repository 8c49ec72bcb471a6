# BlendSR developer entry points. Everything installs into ./.venv (Python 3.11).
PY ?= python3.11
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-stamp
# glibc page-faults every tensor above 32 MB without these (see docs): +25..80% time in torch.
export MALLOC_MMAP_THRESHOLD_ := 4294967296
export MALLOC_TRIM_THRESHOLD_ := 68719476736

.PHONY: setup test test-heavy demo addon bench clean generate constraints

setup: $(STAMP)

# torch's package index: empty uses pip's configuration (PyPI: on Linux its torch is the CUDA build, about 5.7 GB);
# CPU-only machines: make setup TORCH_INDEX=https://download.pytorch.org/whl/cpu (about 200 MB).
TORCH_INDEX ?=
# The torch every install pins (installed first; pinned again beside [dev], whose torchvision would pull the newest).
TORCH_VERSION := 2.13.0
PIP := $(VPY) -m pip install --disable-pip-version-check --progress-bar on
# The tested versions of everything else (constraints.txt): the install resolves at once, the same on every machine.
CONSTRAINTS := -c constraints.txt

# The demo's install: blendsr[demo] (render and train: no test tools, no Triton); 'make setup'/'make test' install
# blendsr[dev] (everything, the test tools and Triton), which the demo then finds in place.
DEMO_STAMP := $(VENV)/.demo-stamp
# make demo THREADS=1: the demo's CPU threads (default: the cores idle when it starts, resources.idle_cores)
THREADS ?=

define venv_torch
	@echo "== setup 1/4: virtual environment $(VENV) (Python 3.11)"
	@test -x $(VPY) || $(PY) -m venv $(VENV)
	@echo "== setup 2/4: pip"
	$(PIP) --quiet --upgrade pip
	@echo "== setup 3/4: torch $(TORCH_VERSION)$(if $(TORCH_INDEX), from $(TORCH_INDEX))"
	# torch first; blendsr's own range (torch>=2.5) is then already satisfied and nothing pulls another build.
	$(PIP) $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) "torch==$(TORCH_VERSION)"
endef

# Re-runs only when pyproject.toml or this Makefile changed; otherwise 'make setup' is a no-op.
$(STAMP): pyproject.toml Makefile constraints.txt
	$(venv_torch)
	@echo "== setup 4/4: blendsr[dev] (bpy is about 820 MB)"
	# torch again: cvvdp's torchvision would otherwise be the newest, pinning (and installing) the newest torch
	$(PIP) $(CONSTRAINTS) -e ".[dev]" "torch==$(TORCH_VERSION)"
	@touch $(STAMP) $(DEMO_STAMP)
	@echo "== setup done: $(VENV)"

$(DEMO_STAMP): pyproject.toml Makefile constraints.txt
	$(venv_torch)
	@echo "== setup 4/4: blendsr[demo] (bpy is about 820 MB; no test tools)"
	$(PIP) $(CONSTRAINTS) -e ".[demo]" "torch==$(TORCH_VERSION)"
	@touch $(DEMO_STAMP)
	@echo "== setup done: $(VENV)"

# make test: the suite without the campaigns and slowest end-to-end cases (marked heavy);
# make test-heavy: those. CI runs both.
# --dist loadfile: a test module runs on one worker, so its module-scoped fixtures (shared renders) are made once.
test: setup
	$(VPY) -m pytest -q -n 2 --dist loadfile --timeout 1200 --durations=15 -m "not heavy"

test-heavy: setup
	$(VPY) -m pytest -q -n 2 --dist loadfile --timeout 2400 --durations=15 -m heavy

demo: $(DEMO_STAMP)
	$(VPY) -m gbuffer_export.cli demo -o demo_out $(if $(THREADS),--threads $(THREADS))

addon: setup
	$(VPY) -m blender_addon.build -o dist

generate: setup
	$(VPY) -m training.commands.generate

bench: setup
	$(VPY) -m gbuffer_export.cli bench render

# constraints.txt again from this .venv (after changing a dependency and checking make test): its comment lines kept;
# torch, triton and nvidia-* left out (the Makefile pins torch; the others follow its build).
constraints: setup
	{ grep '^#' constraints.txt; $(VPY) -m pip freeze --exclude-editable --disable-pip-version-check \
	  | grep -v -E '^(torch|triton)==|^nvidia-'; } > constraints.txt.tmp && mv constraints.txt.tmp constraints.txt

clean:
	rm -rf $(VENV) demo_out dist
