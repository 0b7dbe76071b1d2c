# Developer commands. CI (.ci/run) runs `make check`.
PYTHON ?= python
DOCS_OUT ?= docs/_build/html

.PHONY: check test docs lint types clean-docs

# Everything CI checks, the cheap checks first so that they fail fast: lint, types, the tests, then the documentation
# build with warnings as errors
check: lint types test docs

test:
	$(PYTHON) -m pytest --durations=15

# Quiet on success (-q: warnings and errors only), so that the tests' summary stays the last line of `make check`
docs:
	@$(PYTHON) -m sphinx -q -W --keep-going -b html docs $(DOCS_OUT)

# ruff: Stable-Baselines3's rule set and the formatter (pyproject.toml), on the whole repository
lint:
	$(PYTHON) -m ruff check .
	$(PYTHON) -m ruff format --check .

# mypy on the package, which ships py.typed (settings in pyproject.toml)
types:
	$(PYTHON) -m mypy sb3_dacerf

clean-docs:
	rm -rf docs/_build docs/_generated
