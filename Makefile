# Two commands do all set-up on a fresh machine (each creates/refreshes .venv itself):
#   make demo   - the main job on the built-in synthetic default, end to end
#   make test   - the linter (ruff) and the test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench venv clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m ctcvo demo

test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q -p no:dash

bench: $(STAMP)
	$(PY) -m bench.teacher

clean:
	rm -rf $(VENV) runs .pytest_cache
