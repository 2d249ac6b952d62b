# psdr — two entry points for a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.psdr-installed

SCALE  ?= cpu

.PHONY: demo test install llvm clean help figures fig5 fig6 fig8

help:
	@echo "make demo   set up .venv and run the built-in reconstruction (configs/reconstruct_bunny.yaml) + its evaluation"
	@echo "make test   set up .venv and run the test suite"
	@echo "make figures [SCALE=cpu|paper]   paper reproductions into docs/results/ (so far: fig5, fig6, fig8)"

llvm:
	@bash scripts/ensure-llvm.sh

$(STAMP): pyproject.toml
	@bash scripts/ensure-llvm.sh
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/psdr optimize configs/reconstruct_bunny.yaml
	$(BIN)/psdr evaluate configs/reconstruct_bunny.yaml
	@echo "demo outputs: runs/reconstruct_bunny/ (final.ply, checkpoints/, previews/, log.csv, loss.png, chamfer.png)"

# Paper reproductions (configs/paper/$(SCALE)/, outputs in docs/results/; SCALE=cpu or paper).
# fig9, fig10 and table2 are still to come.
figures: fig5 fig6 fig8

fig5: $(STAMP)
	$(BIN)/psdr guide-stats configs/paper/$(SCALE)/fig5_egg.yaml --guides kdtree

fig6: $(STAMP)
	$(BIN)/psdr compare configs/paper/$(SCALE)/fig6_bunny_sky.yaml
	$(BIN)/psdr compare configs/paper/$(SCALE)/fig6_soft_shadow.yaml
	$(BIN)/psdr compare configs/paper/$(SCALE)/fig6_cornell_glass.yaml

fig8: $(STAMP)
	$(BIN)/psdr compare configs/paper/$(SCALE)/fig8_bunny.yaml

test: $(STAMP)
	$(BIN)/python -m pytest -q tests

clean:
	rm -rf $(VENV) runs build *.egg-info
