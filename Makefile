# Two commands a newcomer needs: `make run` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(VENV)/bin/pip
STAMP  := $(VENV)/.installed

.PHONY: run test docs venv bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# The CPU wheel of torch lies on disk; an unpinned torch would pull a multi-GB CUDA build.
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

# Main job on the embedded default: PE-RLHF with the simulated professional mentor on a ~10-minute
# budget (profile=quick), then the test-split table against IDM-MOBIL. Outputs in runs/pe-rlhf-<time>/.
run: $(STAMP)
	SDL_VIDEODRIVER=dummy $(PY) recipes/pe_rlhf/train.py profile=quick --compare idm-mobil --shield

# A worker per core (pytest-xdist), whole test files per worker so that each module fixture runs once (loadgroup's
# xdist_group does not group under pytest 9: it renames `_nodeid`); then the tests that time themselves, alone,
# so that no other worker steals their cycles (only the files that have such tests are collected again).
test: $(STAMP)
	SDL_VIDEODRIVER=dummy $(PY) -m pytest -q -n auto --dist loadfile -m 'not slow and not timing'
	SDL_VIDEODRIVER=dummy $(PY) -m pytest -q -m timing $$(grep -rl --include='test_*.py' 'mark.timing' tests)
	$(MAKE) --no-print-directory docs

# The docs site (mkdocs.yml, docs/): strict, so a broken link, anchor or docstring fails; built into site/.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet --site-dir site

bench: $(STAMP)
	SDL_VIDEODRIVER=dummy $(PY) benchmarks/env_speed.py

clean:
	rm -rf $(VENV) runs .pytest_cache site
