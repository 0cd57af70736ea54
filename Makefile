# Set-up is part of the product: every target creates .venv when missing and
# installs what the code needs, Debian's libusb-1.0-0 (open3d) included.
VENV    := .venv
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
NPM_STAMP := node_modules/.installed
SUDO    := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
DEBS    := libusb-1.0-0 libgomp1

.PHONY: setup demo test bench schema clean fuzz

$(STAMP): pyproject.toml
	@missing=""; for p in $(DEBS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	fi
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	@touch $(STAMP)

# glTF Transform's CLI and the Khronos validator (package.json) for the glTF attacks and tests;
# Debian's nodejs and npm are installed first where npm is missing.
$(NPM_STAMP): package.json
	@if ! command -v npm >/dev/null 2>&1; then \
	  echo "installing Debian packages: nodejs npm"; \
	  $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nodejs npm; \
	fi
	@major=$$(node -p 'process.versions.node.split(".")[0]'); [ "$$major" -ge 20 ] || \
	  echo "note: node $$major is older than the 20 that @gltf-transform/cli declares"
	npm install --no-audit --no-fund --loglevel=error
	@touch $(NPM_STAMP)

# the package's bytecode written once (compileall writes it even under PYTHONDONTWRITEBYTECODE): each
# test process, Dask worker and CLI run would otherwise compile the sources again (about 0.3 s each)
setup: $(STAMP) $(NPM_STAMP)
	@$(PY) -m compileall -q pipeline

demo: setup
	$(VENV)/bin/pointmark demo

# two test processes side by side (each file's tests in one of them, so a module's world is built once);
# a test process that crashes fails the run: pytest-xdist 3.8's loadfile scheduling can wait forever
# for the replacement of a crashed one (bench/RESULTS.md, "CI's last run")
TEST_JOBS ?= 2
test: setup
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile --no-loadscope-reorder --max-worker-restart=0

bench: setup
	$(PY) bench/run.py

# Each reader fuzz target (tests/fuzz) for FUZZ_SECONDS (default 10 minutes), one after another;
# prints the executions per target.  Needs the real scans of ../shared/data (or POINTMARK_TEST_DATA).
FUZZ_SECONDS ?= 600
fuzz: setup
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 $(PY) -m tests.fuzz.run --seconds $(FUZZ_SECONDS)

schema: setup
	$(VENV)/bin/pointmark schema > configs/schema.json

clean:
	rm -rf $(VENV) node_modules catalog/demo out .pytest_cache
