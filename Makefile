# psdr — two entry points for a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.psdr-installed

SCALE  ?= cpu
# RAY=1 (a local Ray instance), RAY=auto or RAY=ray://HOST:PORT (join a cluster): `psdr optimize`
# and `psdr compare` run each run/variant as one Ray task (installs the optional extra psdr[ray]);
# `make test RAY=1` also runs the Ray tests (CI does).
RAY    ?=
RAY_STAMP := $(VENV)/.psdr-ray-installed
RAYFLAG := $(if $(RAY),--ray$(if $(filter-out 1 local,$(RAY)), $(RAY)),)
DEPS   := $(STAMP) $(if $(RAY),$(RAY_STAMP))

.PHONY: demo test install llvm clean help figures fig5 fig6 fig8 fig9 fig10 table2

help:
	@echo "make demo   set up .venv and run the built-in reconstruction (configs/reconstruct_bunny.yaml) + its evaluation"
	@echo "make test   set up .venv and run the test suite"
	@echo "make figures [SCALE=cpu|paper] [RAY=1|auto|ray://HOST:PORT]   paper reproductions into docs/results/ (fig5 fig6 fig8 fig9 fig10 table2); RAY: runs as Ray tasks"

llvm:
	@bash scripts/ensure-llvm.sh

$(STAMP): pyproject.toml
	@bash scripts/ensure-llvm.sh
	@bash scripts/ensure-chromium.sh
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	@touch $(STAMP)

install: $(STAMP)

$(RAY_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q -e '.[test,ray]'
	@touch $(RAY_STAMP)

demo: $(STAMP)
	$(BIN)/psdr optimize configs/reconstruct_bunny.yaml
	$(BIN)/psdr evaluate configs/reconstruct_bunny.yaml
	@echo "demo outputs: runs/reconstruct_bunny/ (final.ply, checkpoints/, previews/, log.csv, loss.png, chamfer.png)"

# Paper reproductions (configs/paper/$(SCALE)/, outputs in docs/results/; SCALE=cpu or paper).
# fig9/fig10 optimisation runs live in runs/paper/$(SCALE)/ and are resumed when interrupted
# (delete that folder to start them afresh); their reports go to docs/results/.
figures: fig5 fig6 fig8 fig9 fig10 table2

fig5: $(STAMP)
	$(BIN)/psdr guide-stats configs/paper/$(SCALE)/fig5_egg.yaml --guides kdtree

fig6: $(DEPS)
	$(BIN)/psdr compare configs/paper/$(SCALE)/fig6_bunny_sky.yaml $(RAYFLAG)
	$(BIN)/psdr compare configs/paper/$(SCALE)/fig6_soft_shadow.yaml $(RAYFLAG)
	$(BIN)/psdr compare configs/paper/$(SCALE)/fig6_cornell_glass.yaml $(RAYFLAG)

fig8: $(DEPS)
	$(BIN)/psdr compare configs/paper/$(SCALE)/fig8_bunny.yaml $(RAYFLAG)

fig9: $(DEPS)
	$(BIN)/psdr optimize configs/paper/$(SCALE)/fig9_bunny.yaml --resume $(RAYFLAG)
	$(BIN)/psdr evaluate configs/paper/$(SCALE)/fig9_bunny.yaml --report docs/results/fig9_bunny

fig10: $(DEPS)
	$(BIN)/psdr optimize configs/paper/$(SCALE)/fig10_glass.yaml --resume $(RAYFLAG)
	$(BIN)/psdr evaluate configs/paper/$(SCALE)/fig10_glass.yaml --report docs/results/fig10_glass
	$(BIN)/psdr optimize configs/paper/$(SCALE)/fig10_shadow.yaml --resume $(RAYFLAG)
	$(BIN)/psdr evaluate configs/paper/$(SCALE)/fig10_shadow.yaml --report docs/results/fig10_shadow

table2: $(STAMP)
	$(BIN)/psdr table2 configs/paper/$(SCALE)/fig9_bunny.yaml configs/paper/$(SCALE)/fig10_glass.yaml \
		configs/paper/$(SCALE)/fig10_shadow.yaml --out docs/results/table2.md

# The suite runs on every core (pytest-xdist; PYTEST_WORKERS=0 runs it in one process).
# LANES=4|8|16 runs it with Dr.Jit's CPU kernels at that SIMD width (PSDR_LLVM_LANES; default: the
# host's own, 16 with AVX-512, 8 with AVX2), as another machine would (docs/testing.md).
PYTEST_WORKERS ?= auto
LANES  ?=
test: $(DEPS)
	$(if $(LANES),PSDR_LLVM_LANES=$(LANES)) $(BIN)/python -m pytest -q -n $(PYTEST_WORKERS) --dist loadgroup tests

clean:
	rm -rf $(VENV) runs build *.egg-info
