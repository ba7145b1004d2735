# The two commands of the README: `make demo` and `make test`.
# Each creates .venv if it is missing and installs the project with what it needs.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test install browser node-tools bench constraints clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade --quiet pip

# Reinstall whenever the dependencies change.
$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install --quiet -e '.[test,bench]'  # bench: the peers the speed and HDR benchmarks (and their tests) measure against
	touch $(STAMP)

install: $(STAMP)

# The whole chain on simulated devices (daemon, REST run, worker, results, accuracy), in a
# fresh folder under demo-data/ each time; e.g. make demo DEMO_ARGS="--rig rigs/default.toml".
DEMO_ARGS ?=

demo: $(STAMP)
	$(VENV)/bin/mirrorgonio demo $(DEMO_ARGS)

# Debian packages the tests use: chromium, the browser tests/test_web.py drives
# (`playwright install` needs a download site the lab may not reach); docker-compose,
# which tests/test_deploy.py runs to validate docker-compose.yml offline (about 1 MB); and
# postgresql, whose server the catalog's tests start in a throwaway folder of their own
# (its programs live in /usr/lib/postgresql/VERSION/bin, off the PATH: dpkg says it is there).
# The missing ones are installed in one apt step, as root or through sudo.
TEST_DEBS := chromium docker-compose postgresql

browser:
	@missing=; for deb in $(TEST_DEBS); do \
	  command -v $$deb >/dev/null || dpkg -s $$deb >/dev/null 2>&1 || missing="$$missing $$deb"; done; \
	[ -z "$$missing" ] || { \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; \
	  elif command -v sudo >/dev/null; then SUDO=sudo; \
	  else echo "missing:$$missing; installing needs root: apt-get install$$missing" >&2; exit 1; fi; \
	  command -v apt-get >/dev/null || { echo "missing:$$missing and there is no apt-get: install$$missing" >&2; exit 1; }; \
	  echo "installing$$missing (apt-get) for the tests"; \
	  $$SUDO apt-get update && \
	  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $$missing; }

# The Node tools the tests run (tests/js/package.json: the Khronos glTF-Validator), at the
# versions package-lock.json records, from the npm registry; reinstalled when the lock changes.
NODE_TOOLS := tests/js/node_modules/.package-lock.json

$(NODE_TOOLS): tests/js/package-lock.json
	@command -v npm >/dev/null || { echo "npm is missing: the tests validate glTF files with Node (apt-get install nodejs npm)" >&2; exit 1; }
	npm ci --prefix tests/js --silent --no-audit --no-fund
	touch $(NODE_TOOLS)

node-tools: $(NODE_TOOLS)

# The linters first (seconds), then the suite (import-linter's contracts run inside it).
test: $(STAMP) browser $(NODE_TOOLS)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy
	$(PY) -m pytest

# The two cheap benchmarks, their sections of docs/benchmarks.md (a generated file) rewritten.
# The heavy ones (hdr, accuracy, reflectance, tolerance, speed) are run by hand the same way:
# mirrorgonio bench NAME --record docs/benchmarks.md
bench: $(STAMP)
	$(VENV)/bin/mirrorgonio bench render --record docs/benchmarks.md
	$(VENV)/bin/mirrorgonio bench acquire --record docs/benchmarks.md

# constraints.txt, the versions the image installs: a fresh install of the project with its
# gphoto2 extra (and the build's setuptools and wheel) in a throwaway venv, frozen. Run with
# the image's Python (3.11): make constraints CONSTRAINTS_PYTHON=python3.11.
CONSTRAINTS_PYTHON ?= python3.11
CONSTRAINTS_VENV   := build/constraints-venv

constraints:
	rm -rf $(CONSTRAINTS_VENV)
	$(CONSTRAINTS_PYTHON) -m venv $(CONSTRAINTS_VENV)
	$(CONSTRAINTS_VENV)/bin/python -m pip install --quiet --upgrade pip setuptools wheel
	$(CONSTRAINTS_VENV)/bin/python -m pip install --quiet '.[gphoto2]'
	{ echo "# Every package the image installs (Dockerfile: pip install -c constraints.txt), pinned: a fresh"; \
	  echo "# install of the project with its gphoto2 extra on the image's Python (3.11), frozen."; \
	  echo "# Regenerate after changing the dependencies: make constraints (docs/deploy.md)."; \
	  $(CONSTRAINTS_VENV)/bin/python -m pip freeze --all --exclude mirrorgonio --exclude pip; } > constraints.txt
	rm -rf $(CONSTRAINTS_VENV)

clean:
	rm -rf $(VENV) build *.egg-info demo-output demo-data
