# Two commands a newcomer needs: `make run` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(VENV)/bin/pip
STAMP  := $(VENV)/.installed

.PHONY: run test venv bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# The CPU wheel of torch lies on disk; an unpinned torch would pull a multi-GB CUDA build.
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

# Main job on the embedded default (until the training recipe lands: IDM-MOBIL on the test split).
run: $(STAMP)
	SDL_VIDEODRIVER=dummy $(VENV)/bin/pe-rlhf evaluate --policy idm-mobil --split test --episodes 50 --json runs/idm_mobil_test.json

test: $(STAMP)
	SDL_VIDEODRIVER=dummy $(PY) -m pytest -q

bench: $(STAMP)
	SDL_VIDEODRIVER=dummy $(PY) benchmarks/env_speed.py

clean:
	rm -rf $(VENV) runs .pytest_cache
