# Two entry points: `make demo` (set up, then the main job end to end on a synthetic
# drive) and `make test` (set up, then the test suite).
VENV := .venv
BIN := $(VENV)/bin
DEMO := demo

.PHONY: setup demo test bench clean

setup:
	bash scripts/setup.sh

demo: setup
	bash scripts/demo.sh $(DEMO)

test: setup
	$(BIN)/ruff check gtgen pipelines tests bench scripts
	$(BIN)/python -m pytest -n 2 -p no:cacheprovider tests

bench: setup
	for b in bench/*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(DEMO) bench/out
