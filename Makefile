# Two entry points for a fresh machine: `make demo` and `make test`. Both create .venv on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test bench bench-quick clean

$(BIN)/mocap-service: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[dev,bench]"
	touch $@

demo: $(BIN)/mocap-service
	$(BIN)/python -m clients.demo

test: $(BIN)/mocap-service
	$(BIN)/python -m pytest

bench: $(BIN)/mocap-service
	$(BIN)/python -m benchmarks.run

bench-quick: $(BIN)/mocap-service
	$(BIN)/python -m benchmarks.run --quick

clean:
	rm -rf $(VENV) *.egg-info
