# Every target is self-contained on a fresh machine: it creates .venv when missing, installs the
# CPU build of torch first (so no other torch is pulled in), then the package with the extras it needs.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
TORCH_VERSION ?= 2.13.0
PRESET ?= tiny
DEMO_OUT ?= demo-out
REFERENCE_OUT ?= reference-out
PYTEST_ARGS ?=

.PHONY: test demo reference bench lint env clean

$(VENV)/.stamp-torch:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==$(TORCH_VERSION)
	touch $@

$(VENV)/.stamp-dev: $(VENV)/.stamp-torch pyproject.toml
	$(PY) -m pip install --quiet -e ".[dev,ray]"
	touch $@

env: $(VENV)/.stamp-dev

test: $(VENV)/.stamp-dev
	$(PY) -m pytest -n 2 --dist loadfile $(PYTEST_ARGS)

demo: $(VENV)/.stamp-dev
	$(VENV)/bin/relightanyone run pipelines/demo.yaml --var out=$(DEMO_OUT) --var preset=$(PRESET)

# The reference evaluation: the demo pipeline on the `reference` world, every test subject scored.
reference: $(VENV)/.stamp-dev
	$(VENV)/bin/relightanyone run pipelines/demo.yaml --var out=$(REFERENCE_OUT) --var preset=reference \
		--var eval_subjects=0 --var single_stage_share=1

bench: $(VENV)/.stamp-dev
	$(PY) bench/loader.py
	$(PY) bench/synth.py
	$(PY) bench/rasterize.py

lint: $(VENV)/.stamp-dev
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) $(DEMO_OUT) build *.egg-info
