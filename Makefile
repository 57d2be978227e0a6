# pcc_ros: two commands from a fresh clone.
#   make demo   set everything up, then run the end-to-end demo
#   make test   set everything up, then run the whole test suite
# Set-up is idempotent: the venv is (re)built only when requirements.txt or setup.py change;
# scripts/setup_ros.sh adds ROS 2 Jazzy (PyPI wheels + vision_msgs, tf2_msgs built once) unless a ROS 2
# Jazzy environment is sourced, and keeps its own stamps.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.pcc_ros-installed
OUT    ?= out

.PHONY: setup system-deps ros test test-fast test-numpy1 demo bench figures figures-rerun lint clean

setup: system-deps $(STAMP) ros

system-deps:
	@bash scripts/setup_system.sh

# With a ROS 2 environment sourced (ROS_DISTRO), the venv sees the system's packages and keeps its
# numpy (apt's Jazzy on Ubuntu 24.04: 1.26, which its message extensions are built against):
# requirements.txt without its numpy pin, constrained to the numpy already there.
$(STAMP): requirements.txt setup.py
	@test -x $(PY) || $(PYTHON) -m venv $(if $(ROS_DISTRO),--system-site-packages) $(VENV)
	@if [ -n "$(ROS_DISTRO)" ] && $(PY) -c "import numpy" 2>/dev/null; then \
	  $(PY) -c 'import numpy; print("numpy==" + numpy.__version__)' > $(VENV)/numpy-constraint.txt; \
	  echo "ROS_DISTRO=$(ROS_DISTRO): keeping the system's $$(cat $(VENV)/numpy-constraint.txt)"; \
	  grep -v '^numpy==' requirements.txt > $(VENV)/requirements-keep-numpy.txt; \
	  $(PY) -m pip install --disable-pip-version-check -q -r $(VENV)/requirements-keep-numpy.txt \
	    -c $(VENV)/numpy-constraint.txt; \
	else \
	  $(PY) -m pip install --disable-pip-version-check -q -r requirements.txt; \
	fi
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

# numpy 1.26 (apt's Jazzy on Ubuntu 24.04 builds its message extensions against it): a second venv
# whose own numpy 1.26.4 comes before the project venv's packages (the same pins, which all accept
# numpy >= 1.26; the ROS wheels built against numpy 2 run on 1.x), then the tests of the code that
# handles arrays: messages, geometry, the compiled kernels, the pipeline, the node core.
NUMPY1 := .venv-numpy1
NUMPY1_TESTS ?= test/test_msg_pointcloud2.py test/test_msg_detections.py test/test_geometry_boxes.py \
	test/test_filter_evidence.py test/test_pipeline.py test/test_node_core.py test/test_lifecycle.py
test-numpy1: setup
	@test -x $(NUMPY1)/bin/python || $(PY) -m venv --without-pip $(NUMPY1)
	$(PY) -m pip --python $(NUMPY1)/bin/python install --disable-pip-version-check -q numpy==1.26.4
	$(NUMPY1)/bin/python scripts/overlay_venv.py $(VENV)
	$(NUMPY1)/bin/python -c "import numpy; assert numpy.__version__ == '1.26.4', numpy.__version__; print('numpy', numpy.__version__)"
	$(NUMPY1)/bin/python -m pytest -q $(NUMPY1_TESTS)

demo: setup
	$(VENV)/bin/pcc demo --out $(OUT)/demo

bench: setup
	@mkdir -p benchmarks/results
	@for name in $$($(PY) -c 'from benchmarks import available; print(" ".join(available()))'); do \
	  echo "== pcc bench $$name"; \
	  $(VENV)/bin/pcc bench $$name --json benchmarks/results/$$name.json $$([ $$name = soak ] && echo --minutes 5) \
	    || exit 1; \
	done

# the README's and docs' figure tables from a fresh `make bench` (scripts/render_figures.py)
figures: bench
	$(PY) scripts/render_figures.py store-bench benchmarks/results
	$(PY) scripts/render_figures.py

# the docs' evaluation, calibration and check figures: every stored result that is not a benchmark's,
# its recorded command run again (scripts/render_figures.py rerun), then every block re-rendered
figures-rerun:
	$(PY) scripts/render_figures.py rerun

lint: setup
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) $(NUMPY1) build *.egg-info .pytest_cache .ruff_cache
