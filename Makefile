# Two entry points (see README): `make studio` runs the web studio, `make test` runs the tests.
# Each installs what it needs: a virtualenv with pinned packages, the studio's npm build, and for
# the browser test Debian's chromium.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | md5sum | cut -c1-8)
WEB_DIST := src/avatar_motor/serve/static/dist/studio.js

.PHONY: studio test install web chromium clean

install: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	rm -f $(VENV)/.installed-*
	touch $@

web: $(WEB_DIST)

$(WEB_DIST): web/package.json web/package-lock.json $(wildcard web/src/*.js)
	cd web && npm ci --no-audit --no-fund --loglevel=error && npm run build --silent

chromium:
	@command -v chromium >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq chromium >/dev/null)

studio: install web
	$(BIN)/avatar-motor serve --open-browser

test: install web chromium
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)

clean:
	rm -rf $(VENV) web/node_modules src/avatar_motor/serve/static/dist test-artifacts
