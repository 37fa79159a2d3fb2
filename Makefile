# Two entry points (see README): `make studio` runs the web studio, `make test` runs the tests.
# Each installs what it needs: a virtualenv with pinned packages, the studio's npm build, and for
# the browser test Debian's chromium, for the engine and export tests Debian's headless Godot 3 and Blender.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | md5sum | cut -c1-8)
WEB_DIST := src/avatar_motor/serve/static/dist/studio.js

.PHONY: studio test install web chromium godot blender clean models models-check data wheel

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

godot:
	@command -v godot3-server >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq godot3-server >/dev/null)

# FBX export runs Blender; the tests also import glTF with it, whose importer needs numpy
blender:
	@command -v blender >/dev/null 2>&1 && dpkg -s python3-numpy >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq --no-install-recommends blender python3-numpy >/dev/null)

studio: install web
	$(BIN)/avatar-motor serve --open-browser

test: install web chromium godot blender
	$(BIN)/python -m pytest -q $(PYTEST_ARGS)

# dist/avatar_motor-*.whl: the package with the shipped models and the studio, so that
# `pip install dist/avatar_motor-*.whl` then `avatar-motor serve` works in a fresh environment
wheel: install web
	rm -rf build dist src/avatar_motor/_models
	cp -r models src/avatar_motor/_models
	$(BIN)/pip wheel --no-deps -q -w dist . ; status=$$?; rm -rf build src/avatar_motor/_models; exit $$status

clean:
	rm -rf $(VENV) web/node_modules src/avatar_motor/serve/static/dist test-artifacts dist build src/avatar_motor/_models

# The shipped model family, rebuilt in dependency order: the motion data, the base (three stages),
# its one-step EMDM sampler, then the adaptors (actions, styles, reaching) and the persona model
# (the base fine-tuned with text, shape and trajectory conditions), each shipped into
# models/ as float16 with the fingerprint of the base it was trained on. About 9.5 h on 2 CPU
# cores (base 3.5 h + DeepMimic stages 1.3 h, EMDM 1.1 h, actions and styles 2 x 0.5 h, reaching
# 3 seeds x 17 min and the one nearest its targets on other states than its card's kept, persona
# 1.5 h, evaluations); needs ../shared. Starts
# afresh (the runs below are deleted) unless RESUME=1, which continues each interrupted job. A
# shipped folder keeps its card.md: bring its figures up to date from runs/evals/.
SHARED ?= ../shared/data/bandai-namco
PYBULLET ?= pybullet==3.2.7
FAMILY_RUNS := runs/base runs/base-continue runs/base-deepmimic runs/base-deepmimic-2 runs/base-deepmimic-3 runs/emdm runs/adapt-actions runs/adapt-styles runs/adapt-reach runs/adapt-reach-0 runs/adapt-reach-1 runs/adapt-reach-2 runs/persona runs/persona-2
AM := $(BIN)/avatar-motor

data: install
	$(AM) data import $(SHARED)/dataset-1/data
	$(AM) data import $(SHARED)/dataset-2.tar.xz
	$(BIN)/pip download --no-deps -q $(PYBULLET) -d runs/downloads
	$(AM) data import runs/downloads/pybullet-*.whl --name deepmimic

models: data
	$(if $(RESUME),,rm -rf $(FAMILY_RUNS))
	$(AM) limits --config configs/range-of-motion.json
	$(AM) train --config configs/base.json
	$(AM) train --config configs/base-continue.json
	$(AM) train --config configs/base-deepmimic.json
	$(AM) train --config configs/base-deepmimic-2.json
	$(AM) train --config configs/base-deepmimic-3.json
	$(AM) ship runs/base-deepmimic-3/checkpoint models/primal-bandai
	$(AM) distill --config configs/emdm.json
	$(AM) ship runs/emdm/checkpoint models/primal-bandai-emdm --steps 1
	$(AM) adapt --config configs/actions.json
	$(AM) ship runs/adapt-actions/adaptor models/primal-bandai-actions --scale 2.5
	$(AM) adapt --config configs/styles.json
	$(AM) ship runs/adapt-styles/adaptor models/primal-bandai-styles --scale 2.5
	$(AM) adapt --config configs/reach.json --set seed=0 --set out=runs/adapt-reach-0
	$(AM) adapt --config configs/reach.json --set seed=1 --set out=runs/adapt-reach-1
	$(AM) adapt --config configs/reach.json --set seed=2 --set out=runs/adapt-reach-2
	$(AM) eval reach --seed 1 --adaptor-scale 2.5 --adaptors seed0=runs/adapt-reach-0/adaptor seed1=runs/adapt-reach-1/adaptor seed2=runs/adapt-reach-2/adaptor --keep-best runs/adapt-reach/adaptor
	$(AM) ship runs/adapt-reach/adaptor models/primal-bandai-reach --scale 2.5
	$(AM) train --config configs/persona.json
	$(AM) train --config configs/persona-2.json
	$(AM) ship runs/persona-2/checkpoint models/primal-bandai-persona
	mkdir -p runs/evals
	$(AM) eval realism --model models/primal-bandai > runs/evals/realism.txt && cat runs/evals/realism.txt
	$(AM) eval impulses --model models/primal-bandai-emdm > runs/evals/impulses.txt && cat runs/evals/impulses.txt
	$(AM) eval samplers --consistency '' > runs/evals/samplers.txt && cat runs/evals/samplers.txt
	$(AM) eval actions --adaptors actions=models/primal-bandai-actions --evaluators 5 --adaptor-scale 2.5 > runs/evals/actions.txt && cat runs/evals/actions.txt
	$(AM) eval actions --adaptors styles=models/primal-bandai-styles --label-key style --data dataset-2 > runs/evals/styles.txt && cat runs/evals/styles.txt
	$(AM) eval reach --adaptors reach=models/primal-bandai-reach > runs/evals/reach.txt && cat runs/evals/reach.txt
	$(AM) eval persona > runs/evals/persona.txt && cat runs/evals/persona.txt

# The recipe above run end to end in minutes: its commands (make -n) with budgets of a few steps
# (tests/family-check.sed), in a scratch worktree of HEAD (its code, configs and models/, which
# they overwrite), then the family it shipped driven as the studio drives it: the default model
# with the shipped adaptors (a label, a style, a target), and the persona model. Checks that every
# command runs and that each dependent ships on the new base; not the figures. Needs `make data`.
CHECK_DIR ?= /tmp/avatar-motor-models-check
CHECK_ENV = cd $(CHECK_DIR) && AVATAR_MOTOR_MODELS=$(CHECK_DIR)/models PYTHONPATH=$(CHECK_DIR)/src
models-check: install
	rm -rf $(CHECK_DIR) && git worktree prune && git worktree add -f --detach $(CHECK_DIR) HEAD
	ln -s $(abspath $(VENV)) $(CHECK_DIR)/.venv
	$(MAKE) -s -n -C $(CHECK_DIR) models RESUME=1 | sed -E -f tests/family-check.sed > $(CHECK_DIR)/check.sh
	$(CHECK_ENV) bash -c 'mkdir -p runs/evals && bash -ex check.sh'
	$(CHECK_ENV) $(abspath $(AM)) generate --seconds 3 --label bow@0 --label elderly@1 --target 1,1@2 --out runs/family.bvh
	$(CHECK_ENV) $(abspath $(AM)) generate --model models/primal-bandai-persona --persona 'a weary old man' --out runs/persona.bvh
	git worktree remove --force $(CHECK_DIR)
	@echo "models-check: the recipe of make models ran end to end"
