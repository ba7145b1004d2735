# The two commands of the README: `make demo` and `make test`.
# Each creates .venv if it is missing and installs the project with what it needs.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test install browser bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade --quiet pip

# Reinstall whenever the dependencies change.
$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/mirrorgonio demo

# The browser tests/test_web.py drives: Debian's chromium (`playwright install` needs a
# download site the lab may not reach). Installed once, as root or through sudo.
browser:
	@command -v chromium >/dev/null || { \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; \
	  elif command -v sudo >/dev/null; then SUDO=sudo; \
	  else echo "chromium is missing; installing it needs root: apt-get install chromium" >&2; exit 1; fi; \
	  command -v apt-get >/dev/null || { echo "chromium is missing and there is no apt-get: install chromium" >&2; exit 1; }; \
	  echo "installing chromium (apt-get) for the browser tests"; \
	  $$SUDO apt-get update && \
	  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium; }

test: $(STAMP) browser
	$(PY) -m pytest

bench: $(STAMP)
	$(VENV)/bin/mirrorgonio bench render

clean:
	rm -rf $(VENV) build *.egg-info demo-output
