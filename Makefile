# Set-up is automatic: the first target that needs the environment creates .venv,
# installs torch first (TORCH_SPEC: a CPU wheel by default, so pip does not pull
# GBs of CUDA packages), then the project with its train and dev extras.
PYTHON     ?= python3
VENV       ?= .venv
TORCH_SPEC ?= torch==2.13.0
RECIPE     ?= manifests/demo.toml
WORKERS    ?= 2
PYTEST_ARGS ?=
# Test processes (pytest-xdist; logical: one per logical CPU); a test file stays on one process, so its module
# fixtures are built once. A crashed process is not replaced: under --dist loadfile xdist 3.8 can wait forever
# for the replacement's work (pytest-xdist#1378), so the run ends at once and names the test instead.
TEST_WORKERS ?= logical
XDIST = -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --max-worker-restart=0

PY    := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install dataset test test-fast clean splits verify bench train ablate ablate-radar

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install "$(TORCH_SPEC)"
	$(PY) -m pip install -e ".[train,dev]"
	touch $@

install: $(STAMP)

dataset: $(STAMP)
	$(VENV)/bin/meshsar build $(RECIPE) --workers $(WORKERS)

test: $(STAMP)
	$(PY) -m pytest -q $(XDIST) $(PYTEST_ARGS)

test-fast: $(STAMP)
	$(PY) -m pytest -q $(XDIST) -m "not slow" $(PYTEST_ARGS)

clean:
	rm -rf build

OUT ?= build/demo
SEED ?= 0

splits: $(STAMP)
	$(VENV)/bin/meshsar splits $(OUT) --seed $(SEED)

verify: $(STAMP)
	$(VENV)/bin/meshsar verify $(OUT)

PART ?= all

bench: $(STAMP)
	$(VENV)/bin/meshsar bench $(PART)

CONFIG ?= manifests/train/default.toml

train: $(STAMP)
	$(VENV)/bin/meshsar train $(CONFIG) --data $(OUT) --split seed-$(SEED)
	$(VENV)/bin/meshsar evaluate $(OUT)/runs/$(basename $(notdir $(CONFIG)))-seed-$(SEED) --data $(OUT) --split seed-$(SEED)

SEEDS ?= 0,1,2
ABLATE_EPOCHS ?=
# Radar ablation runs trained at once (they share the cores) and its folder (default OUT/ablations/...).
JOBS       ?= 2
ABLATE_OUT ?=

# The radar-loss / pooling / view ablation over seeds on OUT (meshsar ablate); ABLATE_EPOCHS shortens every run.
ablate: $(STAMP)
	$(VENV)/bin/meshsar ablate $(CONFIG) --data $(OUT) --split seed-$(SEED) --seeds $(SEEDS) $(if $(ABLATE_EPOCHS),--epochs $(ABLATE_EPOCHS))

# The radar loss on against off (meshsar ablate --radar): weight chosen on validation, 5 seeds, paired test.
ablate-radar: $(STAMP)
	$(VENV)/bin/meshsar ablate $(CONFIG) --data $(OUT) --split seed-$(SEED) --radar --jobs $(JOBS) $(if $(ABLATE_EPOCHS),--epochs $(ABLATE_EPOCHS)) $(if $(ABLATE_OUT),--out $(ABLATE_OUT))
