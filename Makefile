# Developer commands. CI (.ci/run) runs `make check`.
PYTHON ?= python
DOCS_OUT ?= docs/_build/html

.PHONY: check test docs lint types clean-docs

# Everything CI checks: the tests, then the documentation build with warnings as errors
check: test docs

test:
	$(PYTHON) -m pytest

# Quiet on success (-q: warnings and errors only), so that the tests' summary stays the last line of `make check`
docs:
	@$(PYTHON) -m sphinx -q -W --keep-going -b html docs $(DOCS_OUT)

lint:
	ruff check .
	ruff format --check .

types:
	mypy sb3_dacerf

clean-docs:
	rm -rf docs/_build docs/_generated
