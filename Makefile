# facecap: `make demo` and `make test` set everything up from nothing, then run.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# The ICT Face Model of the synthetic subjects: the trimmed copy in the package (MIT,
# facecap_core/data/README.md), the same for the tests on every machine. Set FACECAP_ICT_MODEL
# (e.g. to the full ict_face_model.npz) to use another for the demo and benchmarks.
ICT_MODEL := $(or $(FACECAP_ICT_MODEL),facecap_core/data/ict_face_model_trimmed.npz)
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
# Shared libraries the wheels need but do not ship (open3d: libusb, libgomp).
SYSTEM_LIBS := libusb-1.0.so.0:libusb-1.0-0 libgomp.so.1:libgomp1
# The iris model (docs/landmarks.md, "Metric scale"), without its declared dependencies: they
# would replace opencv-python-headless's cv2 (pyproject.toml lists what it needs).
MEDIAPIPE := mediapipe==0.10.14

.PHONY: demo test test-fast lint install system-libs compose-tool bench clean

demo: install
	$(PY) -m flows.cli demo --out out/demo --ict-model "$(ICT_MODEL)"

test: install compose-tool
	$(PY) -m pytest -q

# Style and static checks (ruff; its rules are in pyproject.toml).
lint: install
	$(VENV)/bin/ruff check .

# The edit-test loop: everything but the end-to-end renders and stage runs.
test-fast: install compose-tool
	$(PY) -m pytest -q -m "not slow"

install: system-libs $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip setuptools wheel
	$(PY) -m pip install -q -e '.[test]'
	$(PY) -m pip install -q --no-deps $(MEDIAPIPE)
	@touch $@

system-libs:
	@missing=""; for pair in $(SYSTEM_LIBS); do \
	  lib=$${pair%%:*}; pkg=$${pair##*:}; \
	  /sbin/ldconfig -p 2>/dev/null | grep -q "$$lib" || missing="$$missing $$pkg"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq --no-install-recommends $$missing; \
	fi

# The tests validate docker-compose.yml with the compose tool itself; no container engine is
# installed (its recommends are skipped), and the demo does not need the tool at all.
compose-tool:
	@command -v docker-compose >/dev/null || { echo "installing system packages: docker-compose"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq --no-install-recommends docker-compose; }

bench: install
	$(PY) benchmarks/bench_baseline.py

clean:
	rm -rf out .pytest_cache
