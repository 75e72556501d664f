# Two entry points, each self-contained on a fresh machine: `make demo` and `make test`.
VENV ?= .venv
PYTHON ?= python3
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

BENCHMARL_VENV ?= .venv-benchmarl
BENCHMARL_STAMP := $(BENCHMARL_VENV)/.installed

RLLIB_VENV ?= .venv-rllib
RLLIB_STAMP := $(RLLIB_VENV)/.installed

# Peers of `python -m marl_render.bench peers`, each in its own venv (large downloads: TensorFlow
# for Melting Pot). Melting Pot's dmlab2d 1.0.2 has wheels for CPython 3.11 only.
PEERS_PYTHON ?= $(PYTHON)
MELTINGPOT_VENV ?= .venv-meltingpot
MELTINGPOT_STAMP := $(MELTINGPOT_VENV)/.installed
MELTINGPOT_VERSION := 2.4.1
MELTINGPOT_SRC := $(MELTINGPOT_VENV)/src/dm-meltingpot-$(MELTINGPOT_VERSION)
MPE_VENV ?= .venv-mpe
MPE_STAMP := $(MPE_VENV)/.installed
PYBATCHRENDER_VENV ?= .venv-pybatchrender
PYBATCHRENDER_STAMP := $(PYBATCHRENDER_VENV)/.installed
# PyBatchRender is not on PyPI: its git repository (a local clone or mirror works too), at the
# tested commit of its branch clawding (2026-02-13).
PYBATCHRENDER_GIT ?= https://github.com/dolphin-in-a-coma/pybatchrender
PYBATCHRENDER_COMMIT := 3ef046acc65c7d0c49495fa0f354ccc24e8c949f
PEERS_PIP := pip install --quiet --disable-pip-version-check

# Release checks in their own venv: build (isolated, as PyPI users' pip builds), twine and cffconvert.
DIST_VENV ?= .venv-dist
DIST_STAMP := $(DIST_VENV)/.installed
DIST_TOOLS := build==1.6.1 twine==7.0.0 cffconvert==2.0.0

# The GPU kit (see tools/gpu_kit/README.md): built offline-ready into GPU_KIT for a machine with
# Python 3.12, a CUDA torch and no network. PYBATCHRENDER_CLONE, if it exists, goes in too.
GPU_KIT ?= .gpu-kit
PYBATCHRENDER_CLONE ?= $(PYBATCHRENDER_VENV)/src/pybatchrender

.PHONY: demo test docs test-benchmarl test-rllib bench baselines bench-peers peers-venvs meltingpot-venv mpe-venv \
	pybatchrender-venv dist gpu-kit clean

# The venv's packages are installed by uv (pinned, from PyPI): the same pinned set as pip would install,
# in seconds rather than minutes. uv reads no pip configuration, so pip's find-links (where a machine may
# keep its CPU torch wheel) are passed on; without any, both fetch torch from PyPI alike.
UV_VERSION := 0.13.8
PIP_FIND_LINKS_CONFIG = $(shell $(PYTHON) -m pip config get global.find-links 2>/dev/null) $(PIP_FIND_LINKS)

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check uv==$(UV_VERSION)
	$(VENV)/bin/uv pip install --quiet --python $(PY) $(addprefix --find-links ,$(sort $(PIP_FIND_LINKS_CONFIG))) \
		-c constraints.txt -e ".[bench,docs,test,video,jax,sb3,gltf,plots,tensorboard]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) examples/demo.py

# Two pytest workers (pytest-xdist), each test file whole in one of them (--dist loadfile): a module's
# shared fixtures are built once, and its tests run in their written order.
# Bytecode is written even where the environment says not to (PYTHONDONTWRITEBYTECODE, set on some CI
# machines): uv installs no .pyc, and the suite starts many child Pythons that import torch, each of which
# would compile it from source again (5.7 instead of 2.0 CPU-s; torch._dynamo 13 instead of 4).
test: $(STAMP)
	$(PY) -m ruff check .
	env -u PYTHONDONTWRITEBYTECODE $(PY) -m pytest -q -n 2 --dist loadfile

# The docs site (Sphinx + MyST + furo, docs/conf.py) into out/docs/index.html: offline (no intersphinx),
# nitpicky, every warning an error. tests/test_docs.py keeps the build green with Sphinx's dummy builder.
DOCS_OUT ?= out/docs
docs: $(STAMP)
	$(PY) -m sphinx -b html -n -W --keep-going -q docs $(DOCS_OUT)
	@echo "open $(DOCS_OUT)/index.html"

# Second matrix entry: BenchMARL, the torchrl it pins and the CPU torch, in their own venv.
# BenchMARL is installed without its dependencies, which follow by name minus torchvision
# (see constraints-benchmarl.txt for why).
$(BENCHMARL_STAMP): pyproject.toml constraints.txt constraints-benchmarl.txt
	$(PYTHON) -m venv $(BENCHMARL_VENV)
	grep -vE '^(torchrl|tensordict)==' constraints.txt > $(BENCHMARL_VENV)/constraints-main.txt
	$(BENCHMARL_VENV)/bin/pip install --quiet --disable-pip-version-check -c $(BENCHMARL_VENV)/constraints-main.txt \
		-c constraints-benchmarl.txt --no-deps benchmarl
	$(BENCHMARL_VENV)/bin/pip install --quiet --disable-pip-version-check -c $(BENCHMARL_VENV)/constraints-main.txt \
		-c constraints-benchmarl.txt -e ".[test]" torchrl tensordict hydra-core av tqdm numpy
	touch $(BENCHMARL_STAMP)

test-benchmarl: $(BENCHMARL_STAMP)
	$(BENCHMARL_VENV)/bin/python -m pytest -q tests/test_torchrl.py tests/test_benchmarl.py

# Third matrix entry: RLlib on Ray, which pins gymnasium==1.2.2, in its own venv (a large download).
$(RLLIB_STAMP): pyproject.toml constraints.txt constraints-rllib.txt
	$(PYTHON) -m venv $(RLLIB_VENV)
	grep -vE '^gymnasium==' constraints.txt > $(RLLIB_VENV)/constraints-main.txt
	$(RLLIB_VENV)/bin/pip install --quiet --disable-pip-version-check -c $(RLLIB_VENV)/constraints-main.txt \
		-c constraints-rllib.txt -e ".[test]" "ray[rllib]"
	touch $(RLLIB_STAMP)

test-rllib: $(RLLIB_STAMP)
	$(RLLIB_VENV)/bin/python -m pytest -q tests/test_rllib.py

bench: $(STAMP)
	$(PY) -m marl_render.bench render --json

# Every published reference run (marl_render/baselines/published.py: each task from pixels and from
# the state, 3 seeds, step budgets, publication evaluation worlds), one at a time, then docs/baselines.md.
# Hours on 2 cores; a run whose result.json exists is kept. `python -m marl_render.baselines.published`
# lists the commands.
baselines: $(STAMP)
	$(PY) -m marl_render.baselines.published --run

# Melting Pot from its sdist: its build_py downloads bot models from storage.googleapis.com,
# replaced here by an empty assets folder (substrates need no bots; scenarios do and fail).
# The grep fails the build if the patched line was not found.
$(MELTINGPOT_STAMP): constraints-peers-meltingpot.txt
	$(PEERS_PYTHON) -m venv $(MELTINGPOT_VENV)
	rm -rf $(MELTINGPOT_VENV)/src
	$(MELTINGPOT_VENV)/bin/pip download --quiet --disable-pip-version-check --no-deps --no-binary :all: \
		-d $(MELTINGPOT_VENV)/src dm-meltingpot==$(MELTINGPOT_VERSION)
	tar -xzf $(MELTINGPOT_VENV)/src/dm_meltingpot-$(MELTINGPOT_VERSION).tar.gz -C $(MELTINGPOT_VENV)/src
	sed -i 's|^    self\.download_and_extract_assets()$$|    os.makedirs("meltingpot/assets", exist_ok=True)  # no download|' \
		$(MELTINGPOT_SRC)/setup.py
	grep -q 'os.makedirs("meltingpot/assets", exist_ok=True)  # no download' $(MELTINGPOT_SRC)/setup.py
	$(MELTINGPOT_VENV)/bin/$(PEERS_PIP) -c constraints-peers-meltingpot.txt $(MELTINGPOT_SRC) dmlab2d
	touch $(MELTINGPOT_STAMP)

$(MPE_STAMP): constraints-peers-mpe.txt
	$(PEERS_PYTHON) -m venv $(MPE_VENV)
	$(MPE_VENV)/bin/$(PEERS_PIP) -c constraints-peers-mpe.txt mpe2
	touch $(MPE_STAMP)

# With marl-render's own pins (constraints.txt): the CPU torch 2.13.0, torchrl, panda3d.
$(PYBATCHRENDER_STAMP): constraints.txt constraints-peers-pybatchrender.txt
	$(PEERS_PYTHON) -m venv $(PYBATCHRENDER_VENV)
	rm -rf $(PYBATCHRENDER_VENV)/src
	git clone --quiet $(PYBATCHRENDER_GIT) $(PYBATCHRENDER_VENV)/src/pybatchrender
	git -C $(PYBATCHRENDER_VENV)/src/pybatchrender checkout --quiet $(PYBATCHRENDER_COMMIT)
	$(PYBATCHRENDER_VENV)/bin/$(PEERS_PIP) -c constraints.txt -c constraints-peers-pybatchrender.txt \
		$(PYBATCHRENDER_VENV)/src/pybatchrender
	touch $(PYBATCHRENDER_STAMP)

meltingpot-venv: $(MELTINGPOT_STAMP)
mpe-venv: $(MPE_STAMP)
pybatchrender-venv: $(PYBATCHRENDER_STAMP)
peers-venvs: meltingpot-venv mpe-venv pybatchrender-venv

# Writes docs/bench/peers.json and peers.md (a few minutes; run it on a quiet machine).
bench-peers: $(STAMP) peers-venvs
	$(PY) -m marl_render.bench peers --meltingpot-venv $(MELTINGPOT_VENV) --mpe-venv $(MPE_VENV) \
		--pybatchrender-venv $(PYBATCHRENDER_VENV) --out docs/bench

$(DIST_STAMP):
	$(PYTHON) -m venv $(DIST_VENV)
	$(DIST_VENV)/bin/pip install --quiet --disable-pip-version-check $(DIST_TOOLS)
	touch $(DIST_STAMP)

# dist/: the sdist and the wheel, checked by twine; CITATION.cff against its schema.
dist: $(DIST_STAMP)
	rm -rf dist marl_render.egg-info  # an old egg-info's SOURCES.txt would add its files to the sdist
	$(DIST_VENV)/bin/python -m build --outdir dist .
	$(DIST_VENV)/bin/twine check --strict dist/*
	$(DIST_VENV)/bin/cffconvert --validate -i CITATION.cff

gpu-kit: $(STAMP)
	$(PY) tools/gpu_kit/build.py --out $(GPU_KIT) --pybatchrender $(PYBATCHRENDER_CLONE)

clean:
	rm -rf $(VENV) $(BENCHMARL_VENV) $(RLLIB_VENV) $(MELTINGPOT_VENV) $(MPE_VENV) $(PYBATCHRENDER_VENV) $(DIST_VENV) \
		out dist $(GPU_KIT)
