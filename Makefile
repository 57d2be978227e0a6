# pcc_ros: two commands from a fresh clone.
#   make demo   set everything up, then run the end-to-end demo
#   make test   set everything up, then run the whole test suite
# Set-up is idempotent: the venv is (re)built only when requirements.txt or setup.py change;
# scripts/setup_ros.sh adds ROS 2 Jazzy (PyPI wheels + vision_msgs built once) unless a ROS 2
# Jazzy environment is sourced, and keeps its own stamps.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.pcc_ros-installed
OUT    ?= out

.PHONY: setup system-deps ros test test-fast demo bench figures lint clean

setup: system-deps $(STAMP) ros

system-deps:
	@bash scripts/setup_system.sh

$(STAMP): requirements.txt setup.py
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q -r requirements.txt
	$(PY) -m pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e .
	@touch $@

ros: $(STAMP)
	@bash scripts/setup_ros.sh $(VENV)

# pytest exits 5 when it collected nothing: say so loudly instead of failing make with a bare 2.
test: setup
	@$(PY) -m pytest; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests"; exit 0; fi; exit $$rc

test-fast: setup
	$(PY) -m pytest -m "not slow"

demo: setup
	$(VENV)/bin/pcc demo --out $(OUT)/demo

bench: setup
	@mkdir -p benchmarks/results
	@for name in $$($(PY) -c 'from benchmarks import available; print(" ".join(available()))'); do \
	  echo "== pcc bench $$name"; \
	  $(VENV)/bin/pcc bench $$name --json benchmarks/results/$$name.json || exit 1; \
	done

# the README's and docs' figure tables from a fresh `make bench` (scripts/render_figures.py)
figures: bench
	$(PY) scripts/render_figures.py store-bench benchmarks/results
	$(PY) scripts/render_figures.py

lint: setup
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
