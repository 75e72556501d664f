# Two entry points, each self-contained on a fresh machine: `make demo` and `make test`.
VENV ?= .venv
PYTHON ?= python3
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

BENCHMARL_VENV ?= .venv-benchmarl
BENCHMARL_STAMP := $(BENCHMARL_VENV)/.installed

RLLIB_VENV ?= .venv-rllib
RLLIB_STAMP := $(RLLIB_VENV)/.installed

.PHONY: demo test test-benchmarl test-rllib bench clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[bench,test,video,jax,sb3,gltf]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) examples/demo.py

test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m pytest -q

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

clean:
	rm -rf $(VENV) $(BENCHMARL_VENV) $(RLLIB_VENV) out
