# Two commands do all set-up on a fresh machine (Python 3.11 with venv):
#   make run    synthesize and verify the design table, then drive the dry-to-snow route
#               certified vs base under a stability attack (plot, Meshcat page, tape)
#   make test   run the test suite (fast tests; `make test-slow` runs the rest)
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test test-slow bench lint notebooks docs clean

$(STAMP): pyproject.toml constraints.txt
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e '.[dev,ray,onnx,docs]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/drake-cert synthesize --out results/designs.yaml
	$(BIN)/drake-cert verify results/designs.yaml --complete
	$(BIN)/drake-cert drive --scenario dry_to_snow --compare --attack sa --designs results/designs.yaml \
		--plot results/drive.png --meshcat results/drive.html --out results/drive.csv
	@echo "Over more seeds (benchmarks/seed_study.py, committed in docs/seed_study/):"
	@grep -h "left its lane" docs/seed_study/dry_to_snow.md

# Two workers, one per core; a test file runs whole on one worker (its module fixtures are
# computed once). The suite must stay under 8 min on 2 cores; the 15 slowest are printed.
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=15

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow -n 2 --dist loadfile --durations=15

bench: $(STAMP)
	for f in benchmarks/bench_*.py; do $(BIN)/python $$f || exit 1; done

notebooks: $(STAMP)
	$(BIN)/python notebooks/execute.py

# The documentation site (mkdocs + mkdocstrings, API reference from the docstrings) in site/;
# strict: a broken link or reference fails the build. tests/test_docs_site.py builds it too.
docs: $(STAMP)
	$(BIN)/mkdocs build --strict

lint: $(STAMP)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) results site
