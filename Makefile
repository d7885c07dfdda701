# Two commands do all set-up on a fresh machine (Python 3.11 with venv):
#   make run    synthesize and verify the design table, then drive the dry-to-snow route
#               certified vs base under a stability attack (plot, Meshcat page, tape)
#   make test   run the test suite (fast tests; `make test-slow` runs the rest)
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test test-slow bench lint notebooks clean

$(STAMP): pyproject.toml constraints.txt
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e '.[dev,ray,onnx]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/drake-cert synthesize --out results/designs.yaml
	$(BIN)/drake-cert verify results/designs.yaml --complete
	$(BIN)/drake-cert drive --scenario dry_to_snow --compare --attack sa --designs results/designs.yaml \
		--plot results/drive.png --meshcat results/drive.html --out results/drive.csv

test: $(STAMP)
	$(BIN)/python -m pytest -q --durations=15  # the 15 slowest: the suite must stay under 10 min on 2 cores

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow --durations=15

bench: $(STAMP)
	for f in benchmarks/bench_*.py; do $(BIN)/python $$f || exit 1; done

notebooks: $(STAMP)
	$(BIN)/python notebooks/execute.py

lint: $(STAMP)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) results
