# hycontrol-vision — every target installs what it needs first (`make setup` is a stamp-file no-op when up to date).
SHELL := /bin/bash
.DEFAULT_GOAL := help
PY_BOOT ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-stamp
# Large-tensor allocations without page-fault storms: ~2.5x faster CPU training (see README, "Speed").
export GLIBC_TUNABLES ?= glibc.malloc.hugetlb=1
export PYTHONHASHSEED := 0
ARGS ?=

help: ## list the targets
	@grep -hE '^[a-zA-Z_-]+:.*?## ' $(MAKEFILE_LIST) | awk 'BEGIN{FS=":.*?## "}{printf "  \033[36m%-14s\033[0m %s\n", $$1, $$2}'

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PY_BOOT) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP) ## create .venv and install the project (no-op when nothing changed)

run: paper ## the main job: regenerate every figure and table of the paper (alias of `make paper`)

paper: $(STAMP) ## data -> train -> errormap -> experiments; writes outputs/paper/ (ARGS=debug=tiny: all of it in minutes)
	$(PY) -m pipeline.paper $(ARGS)

multi: $(STAMP) ## several obstacles + the unicycle (issue 19): their data -> train -> errormap -> experiments
	$(PY) -m pipeline.paper --config-name multi $(ARGS)

dagger: $(STAMP) ## DAgger-style rounds: data -> train -> closed loop with the map -> aggregated data -> ... (outputs/dagger/)
	$(PY) -m pipeline.dagger $(ARGS)

generalisation: $(STAMP) ## maps on every cloud level (issue 11): authors + clean_paper maps, tab_perception_generalisation
	$(PY) -m pipeline.paper --config-name paper_generalisation $(ARGS)

learned: $(STAMP) ## learned end-to-end policies (SPEC §6): imitate the hybrid controller (BC + DAgger, clean and clouded; ARGS), PPO, then compare them with the paper's architecture (LEARNED_ARGS) in outputs/learned/
	$(PY) -m pipeline.learned.imitate $(ARGS)
	$(PY) -m pipeline.learned.imitate --config-name imitate_heavy $(ARGS)
	$(PY) -m pipeline.learned.ppo
	$(PY) -m pipeline.learned.evaluate $(LEARNED_ARGS)

simulate: $(STAMP) ## closed-loop simulation demo on the true state (Hydra: make simulate ARGS="controller=smooth")
	$(PY) -m pipeline.simulate $(ARGS)

data: $(STAMP) ## render the tracked camera datasets (clean, occluded, leader_follower)
	$(PY) -m pipeline.data -m data=clean,occluded,leader_follower $(ARGS)

verify-data: $(STAMP) ## re-hash every dataset and report missing/altered files
	$(PY) -m pipeline.data.verify $(ARGS)

train: $(STAMP) ## train make paper's perception maps (keypoint head) on clean and occluded data (make run trains them side by side)
	$(PY) -m pipeline.train -m data=clean,occluded model=keypoint $(ARGS)

errormap: $(STAMP) ## epsilon-error maps, Lipschitz estimate and Assumption-1 coverage
	$(PY) -m pipeline.errormap $(ARGS)

bracket: $(STAMP) ## the closed loop bracketed: certified eps_lo and falsified eps_hi per controller and start cell (outputs/bracket/)
	$(PY) -m pipeline.bracket hydra.run.dir=outputs/bracket/default $(ARGS)

certify: $(STAMP) ## certified error maps: sound bounds of the perception error over cells (SPEC 5.1-5.3; docs/certify.md)
	$(PY) -m pipeline.certify $(ARGS)

certify-clouds: $(STAMP) ## certified error maps under clouds: eps_bar_delta per cell over the level's layouts (issue 44; docs/certify.md)
	$(PY) -m pipeline.certify.clouds_cli $(ARGS)

experiments: $(STAMP) ## every scenario of make paper (figures under outputs/side/<experiment>-<id>/; ARGS=publish=true: outputs/paper/)
	$(PY) -m pipeline.experiments -m 'experiment=glob(*,exclude=[perception_generalisation,multi_*,unicycle*,dense_*,camera_attack_sweep,worst_cloud_sweep,geometry_margin_grid])' $(ARGS)

# The tests' ~120 short processes run without the huge pages: none needs them (docs/speed.md §17).
test: $(STAMP) ## fast test suite (< 10 min on 2 cores: one pytest-xdist worker per core)
	GLIBC_TUNABLES= $(PY) -m pytest -q -n auto --dist worksteal $(ARGS)

test-explore: $(STAMP) ## property tests with fresh random examples each run (finds new counter-examples)
	HYPOTHESIS_PROFILE=explore $(PY) -m pytest -q -m '' -k 'not slow' $(ARGS) $$(grep -l hypothesis tests/*.py)

test-all: $(STAMP) ## every test, slow ones included
	GLIBC_TUNABLES= $(PY) -m pytest -q -n auto --dist worksteal -m '' $(ARGS)

bench: $(STAMP) ## speed benchmarks, printed as a table
	$(PY) -m pipeline.bench $(ARGS)

lint: $(STAMP) ## ruff
	$(PY) -m ruff check pipeline tests

docs-check: $(STAMP) ## which map ids quoted in README.md and docs/*.md the current code still gives; tables without date or command (a report)
	$(PY) -m pipeline.docs_check $(ARGS)

clean: ## remove generated data and outputs (keeps .venv)
	rm -rf data/datasets outputs/* && touch outputs/.gitkeep

.PHONY: help setup run paper multi dagger generalisation learned simulate data verify-data train errormap certify certify-clouds bracket experiments test test-all bench lint docs-check clean
