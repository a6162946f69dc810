# Two entry points for a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test lint venv robot-venv clean

# The robots' Python: the oldest that onboard/ supports (3.9), with the oldest releases of its packages that
# pyproject.toml allows (numpy's last 1.22). `make test` builds it when it finds a Python 3.9 (or ROBOT_PYTHON
# names one); tests/test_robot_python.py runs lab-6-payload's agents on it (`khepri sil --agent-python`) and
# test_kh4_driver.py the driver's stop-on-exit. Without one, those tests are skipped and say why.
ROBOT_VENV     := .venv-robot
ROBOT_STAMP    := $(ROBOT_VENV)/.installed
ROBOT_PACKAGES := numpy==1.22.4 pyzmq==25.0.0 pyyaml==6.0 filterpy==2.0.0
ROBOT_PYTHON   ?=

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

# Re-install when the project definition changes.
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/khepri sim run lab-6 --out out/demo --video out/demo/run.gif

# The suite runs in TEST_JOBS processes (pytest-xdist): 2 fills the 2-core development machine. More than the
# cores slows the tests that time real agents and hubs; TEST_JOBS=0 runs it in this process, in file order.
TEST_JOBS ?= 2

test: $(STAMP) robot-venv
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -n $(TEST_JOBS)

robot-venv: $(ROBOT_STAMP)

$(ROBOT_STAMP): pyproject.toml
	@py="$(ROBOT_PYTHON)"; \
	if [ -z "$$py" ]; then \
	  for candidate in python3.9 $$HOME/.pyenv/versions/3.9*/bin/python3.9; do \
	    if "$$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 9))' 2>/dev/null; then \
	      py=$$candidate; break; fi; \
	  done; \
	fi; \
	if [ -z "$$py" ]; then \
	  echo "robot-venv: no Python 3.9 found (set ROBOT_PYTHON=...): the robots' Python will not be tested"; \
	else \
	  rm -rf $(ROBOT_VENV); \
	  if "$$py" -m venv $(ROBOT_VENV) && $(ROBOT_VENV)/bin/pip install --quiet $(ROBOT_PACKAGES); then \
	    touch $@; \
	  else \
	    rm -rf $(ROBOT_VENV); \
	    echo "robot-venv: could not install $(ROBOT_PACKAGES) for $$py: the robots' Python will not be tested"; \
	  fi; \
	fi

lint: $(STAMP)
	$(BIN)/ruff check .

clean:
	rm -rf out build *.egg-info
