# Two entry points: `make demo` (set up, then the main job end to end on a synthetic
# drive) and `make test` (set up, then the test suite); `make docs` builds the site.
VENV := .venv
BIN := $(VENV)/bin
DEMO := demo

.PHONY: setup demo test docs bench clean

setup:
	bash scripts/setup.sh

demo: setup
	bash scripts/demo.sh $(DEMO)

test: setup
	$(BIN)/ruff check gtgen pipelines tests bench scripts
	$(BIN)/python -m pytest -n 2 --dist worksteal -p no:cacheprovider tests

# the docs group is installed only where it is missing; --strict fails on a broken link,
# anchor or include, and on a reference page the code cannot generate
docs: setup
	$(BIN)/python -c "import mkdocs, material, mkdocstrings_handlers.python" 2>/dev/null || PIP_RETRIES=10 PIP_RESUME_RETRIES=20 $(BIN)/python -m pip install -q -e ".[docs]"
	$(BIN)/mkdocs build --strict --site-dir site

bench: setup
	for b in bench/*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(DEMO) bench/out site
