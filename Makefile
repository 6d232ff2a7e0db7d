# Two commands do all set-up on a fresh machine:  make demo   and   make test
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= out

# the venv is an ament prefix (the ROS wheels put share/ament_index there)
export AMENT_PREFIX_PATH := $(abspath $(VENV))
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST

.PHONY: all venv test test-long demo plan bench clean

all: test

$(STAMP): requirements.txt setup.py setup.cfg package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	$(PY) -m spacerobot_planner.ament_install --prefix $(VENV)
	touch $(STAMP)

venv: $(STAMP)

test: venv
	$(PY) -m pytest -q

test-long: venv
	$(PY) -m pytest -q --hypothesis-profile=long

demo: venv
	$(PY) -m spacerobot_planner.demo --out $(OUT)

plan: venv
	$(VENV)/bin/spacerobot-plan --params-file config/paper_3dof.yaml --plot $(OUT)/paper_3dof.png

bench: venv
	$(PY) -m spacerobot_planner.bench all

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .hypothesis build *.egg-info
