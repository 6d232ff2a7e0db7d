# Two commands do all set-up on a fresh machine:  make demo   and   make test
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= out

# the venv is an ament prefix (the ROS wheels put share/ament_index there)
export AMENT_PREFIX_PATH := $(abspath $(VENV))
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST

IFACE  := interfaces/spacerobot_planner_interfaces
# every scenario file: numba's cache gets each one's route (2-D, 3-D, 4-D grids; free-floating capture)
CONFIGS := $(sort $(wildcard config/*.yaml))
IFACE_BUILD := build/interfaces
VENV_ABS := $(abspath $(VENV))

.PHONY: all venv interfaces test test-long demo plan bench clean

all: test

# 1. the wheels; 2. the interface package (CMake, into the venv prefix, as colcon would);
# 3. this package (editable) and its ament layout; 4. numba's cache of each scenario file's route and
# the package's bytecode (worker --warm-cache)
$(STAMP): requirements.txt setup.py setup.cfg package.xml $(IFACE)/CMakeLists.txt $(IFACE)/package.xml \
		$(wildcard $(IFACE)/action/*.action)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	$(MAKE) interfaces
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	$(PY) -m spacerobot_planner.tools.ament_install --prefix $(VENV)
	$(PY) -m spacerobot_planner.worker --warm-cache $(CONFIGS)
	touch $(STAMP)

interfaces:
	mkdir -p $(IFACE_BUILD)
	PATH="$(VENV_ABS)/bin:$$PATH" cmake -S $(IFACE) -B $(IFACE_BUILD) -DBUILD_TESTING=OFF \
		-DCMAKE_PREFIX_PATH=$(VENV_ABS) -DCMAKE_INSTALL_PREFIX=$(VENV_ABS) \
		-DPython3_EXECUTABLE=$(VENV_ABS)/bin/python > $(IFACE_BUILD).log 2>&1 || (cat $(IFACE_BUILD).log; exit 1)
	cmake --build $(IFACE_BUILD) -j2 >> $(IFACE_BUILD).log 2>&1 || (tail -50 $(IFACE_BUILD).log; exit 1)
	cmake --install $(IFACE_BUILD) >> $(IFACE_BUILD).log 2>&1 || (tail -50 $(IFACE_BUILD).log; exit 1)

venv: $(STAMP)

# the suite mostly waits (discovery, plans, arm motions): 3 worker processes on 2 cores, each
# with a ROS domain of its own (test/conftest.py); slow tests are handed out first
PYTEST_WORKERS ?= 3

test: venv
	$(PY) -m pytest -q -n $(PYTEST_WORKERS)

test-long: venv
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) --hypothesis-profile=long

demo: venv
	$(PY) -m spacerobot_planner.tools.demo --out $(OUT)

plan: venv
	$(VENV)/bin/spacerobot-plan --params-file config/paper_3dof.yaml --plot $(OUT)/paper_3dof.png

bench: venv
	$(PY) -m spacerobot_planner.bench all

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .hypothesis build *.egg-info
