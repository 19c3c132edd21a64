# hmpf — common tasks. Everything installs into .venv on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
DATASETS ?= $(abspath ../shared/datasets)
export HMPF_DATASETS ?= $(DATASETS)
# a preset name (hmpf/presets/, browsable as configs/) or a path to a YAML file
CONFIG ?= default
REFERENCE ?= $(HMPF_DATASETS)/gardens_point/day_right
QUERY ?= $(HMPF_DATASETS)/gardens_point/night_right
TOLERANCE ?= 2
INDEX ?= index/default
HOST ?= 127.0.0.1
PORT ?= 8000
PIP_INSTALL := $(VENV)/bin/pip install --disable-pip-version-check -q
# torch: the CPU build, asked for explicitly (PyPI's torch wheel for Linux is a multi-GB CUDA
# build). From the PyTorch CPU index when it answers; else from pip's own indexes (here: the
# CPU wheel on this machine's disk). Either way the install fails if torch has CUDA.
TORCH_VERSION ?= 2.13.0
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu

.PHONY: install run index clean-index eval test test-offline browser haproxy bench lint format clean \
	container container-test docs

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PIP_INSTALL) --upgrade pip
	@# opencv-contrib-python-headless replaced opencv-python-headless (the same cv2 module):
	@# an old venv's plain wheel goes first; contrib is reinstalled if that removed its files.
	$(VENV)/bin/pip uninstall -y -q opencv-python-headless 2>/dev/null || true
	if $(PY) -c 'import sys, urllib.request; urllib.request.urlopen(sys.argv[1] + "/torch/", timeout=5)' \
		$(TORCH_INDEX) 2>/dev/null; then \
		$(PIP_INSTALL) torch==$(TORCH_VERSION) --index-url $(TORCH_INDEX); \
	else $(PIP_INSTALL) torch==$(TORCH_VERSION); fi
	$(PY) -c 'import torch, sys; sys.exit(f"torch {torch.__version__} is a CUDA build" if torch.version.cuda else 0)'
	$(PIP_INSTALL) -e '.[dev,cnn,index,service,report,ray,openvino]'
	$(PY) -c 'import cv2; cv2.xfeatures2d.TEBLID_create' 2>/dev/null || $(PIP_INSTALL) \
		--force-reinstall --no-deps "$$($(VENV)/bin/pip list --format=freeze | grep -i '^opencv-contrib')"
	$(PY) -c 'import cv2; cv2.xfeatures2d.TEBLID_create'
	touch $@

install: $(VENV)/.installed

## run: build the default index over $(REFERENCE) unless $(INDEX) has one, then serve it on
## $(HOST):$(PORT). Authentication is off here, explicitly (a warning is logged); serve with
## keys: make run HMPF_AUTH=true HMPF_KEYS_FILE=keys.yaml (see hmpf-serve keys add).
run: index
	HMPF_AUTH=$${HMPF_AUTH:-false} $(VENV)/bin/hmpf-serve --index $(INDEX) --host $(HOST) --port $(PORT)

## index: build $(INDEX) from $(REFERENCE) with $(CONFIG) if it has no current version
index: install
	@if [ -f $(INDEX)/CURRENT ]; then echo "index $(INDEX) exists (version $$(cat $(INDEX)/CURRENT)); make clean-index to rebuild"; \
	else $(VENV)/bin/hmpf-index build --config $(CONFIG) --images $(REFERENCE) --index $(INDEX); fi

clean-index:
	rm -rf $(INDEX)

## eval: evaluate $(CONFIG) on Gardens Point day_right -> night_right, write results/eval.json
eval: install
	$(VENV)/bin/hmpf-eval --config $(CONFIG) --reference $(REFERENCE) --query $(QUERY) \
		--tolerance $(TOLERANCE) --json results/eval.json

## test: the whole test suite (fails when no test is collected), on TEST_WORKERS processes
## (pytest-xdist; TEST_WORKERS=0: one process)
TEST_WORKERS ?= 2
PYTEST_WORKERS = -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder
test: install
	$(PY) -m pytest -q $(PYTEST_WORKERS)

## browser: the system chromium the inspection page's browser test drives (tests/service/test_inspect.py;
## Playwright's own browser download is not used). Installed with apt-get when missing (root).
browser:
	@command -v chromium >/dev/null || { \
		SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends chromium >/dev/null; }
	@chromium --version 2>/dev/null

## haproxy: the load balancer tests/service/test_replicas.py puts in front of two hmpf-serve replicas
## (docs/replicas.md). Installed with apt-get when missing (root).
haproxy:
	@PATH="$$PATH:/usr/sbin:/sbin" command -v haproxy >/dev/null || { \
		SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends haproxy >/dev/null; }
	@PATH="$$PATH:/usr/sbin:/sbin" haproxy -v | head -n 1

## container: the indexer and service images (localhost/hmpf-indexer:dev, localhost/hmpf-service:dev)
## built with podman on a local Debian bookworm base (docker/local-base.sh, mmdebstrap), for
## machines with no container registry. podman, runc, mmdebstrap and curl are installed with
## apt-get when missing (root). docs/deployment-container.md
## container-test: the same build (tag test), then the indexer job over Gardens Point
## day_right ($(HMPF_DATASETS), mounted read-only), the service with API keys, and a night frame
## localized through its port (docker/container-test.sh); RECORD=path writes the run as a JSON
## record (docs/deployment-container.md, "Measured")
CONTAINER_TOOLS = @PATH="$$PATH:/usr/sbin:/sbin"; \
	command -v podman >/dev/null && command -v runc >/dev/null && \
	command -v mmdebstrap >/dev/null && command -v curl >/dev/null || { \
		SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends \
			podman runc mmdebstrap curl >/dev/null; }

container:
	$(CONTAINER_TOOLS)
	PATH="$$PATH:/usr/sbin:/sbin" TAG=dev docker/container-test.sh --build-only

container-test:
	$(CONTAINER_TOOLS)
	PATH="$$PATH:/usr/sbin:/sbin" docker/container-test.sh

## test-offline: the tests that need no dataset (pytest -m "not dataset")
test-offline: install
	$(PY) -m pytest -q -m "not dataset" $(PYTEST_WORKERS)

bench: install
	$(PY) -m bench.accuracy --out results/accuracy.json

lint: install
	$(VENV)/bin/ruff check hmpf indexer service tests bench
	$(VENV)/bin/ruff format --check hmpf indexer service tests bench
	$(VENV)/bin/mypy hmpf indexer service
	$(VENV)/bin/hadolint docker/Dockerfile

## docs: the documentation site from docs/ (mkdocs.yml: MkDocs, Material, mkdocstrings) into site/,
## offline; --strict: a broken link or any other warning fails the build
docs: install
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

format: install
	$(VENV)/bin/ruff format hmpf indexer service tests bench
	$(VENV)/bin/ruff check --fix hmpf indexer service tests bench

clean:
	rm -rf $(VENV) results .pytest_cache .ruff_cache
