# Two commands matter: `make demo` (the main job, against the simulators) and `make test`.
# Both create .venv when it is missing or older than pyproject.toml, and install the project.
PY ?= python3
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench venv clean docs

$(STAMP): pyproject.toml
	@test -x $(VENV)/bin/python || $(PY) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --upgrade pip
	$(VENV)/bin/python -m pip install -q -e '.[test]'
	@touch $(STAMP)

venv: $(STAMP)

# exit 3 is `complete with defects` (docs/controller.md): the demo prints them and writes the record
demo: $(STAMP)
	$(VENV)/bin/cell demo || [ $$? -eq 3 ]

# three workers on two cores: most tests wait on a simulated device's clock, not on a CPU
# (two workers kept the CPUs about half busy); docs/testing.md
test: $(STAMP)
	$(VENV)/bin/python -m pytest -q -n 3 --dist loadfile --durations=25

# ruff, mypy and the import contracts (docs/architecture.md)
lint: $(STAMP)
	PY=$(VENV)/bin/python .ci/lint

bench: $(STAMP)
	$(VENV)/bin/python -m bench

docs: $(STAMP)
	$(VENV)/bin/cell docs

clean:
	rm -rf $(VENV) runs .pytest_cache
