# Graylight: `make demo` sets everything up and scans, merges and publishes a whole object; `make test` runs the suite.
SHELL := /bin/bash
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.graylight-installed
KERNELS := $(VENV)/.graylight-kernels
# Debian packages the project needs: EGL/Mesa for headless OpenGL, Chromium for the viewer
# test, Redis for the broker. Node and npm (viewer assets) are installed only when missing,
# since a machine may carry another build of Node that ships its own npm.
APT_PACKAGES := libegl1 libgl1-mesa-dri chromium redis-server libusb-1.0-0
PYTEST_WORKERS ?= 2

.PHONY: setup demo test test-fast bench lint services clean

setup: $(STAMP) $(KERNELS)

# numba's cache (__pycache__ beside each module, or NUMBA_CACHE_DIR) filled for every kernel
# signature the pipeline uses, so that no first run compiles; redone when a source changes.
$(KERNELS): $(STAMP) $(shell find shared workers -name "*.py" 2>/dev/null)
	$(BIN)/python -m workers.warmup
	@touch $(KERNELS)

$(STAMP): pyproject.toml Makefile $(wildcard services/viewer/package-lock.json)
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	command -v npm >/dev/null 2>&1 || missing="$$missing nodejs npm"; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing; \
	fi
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip >/dev/null
	$(BIN)/python -m pip install -q -e '.[dev]'
	@if [ -f services/viewer/package.json ]; then $(MAKE) --no-print-directory viewer; fi
	@touch $(STAMP)

.PHONY: viewer
viewer:
	@if [ -f services/viewer/package.json ]; then \
	  cd services/viewer && npm ci --no-audit --no-fund --loglevel=error && npm run --silent build; \
	fi

# Start the local Redis and PostgreSQL the tests use, when they are not running.
services:
	@redis-cli -h 127.0.0.1 -p 6379 ping >/dev/null 2>&1 || \
	  redis-server --daemonize yes --bind 127.0.0.1 --port 6379 --save "" --appendonly no
	@for i in $$(seq 50); do redis-cli -h 127.0.0.1 -p 6379 ping >/dev/null 2>&1 && break; sleep 0.1; done
	@if command -v pg_isready >/dev/null && ! pg_isready -q -h 127.0.0.1 -p 5432; then \
	  command -v pg_ctlcluster >/dev/null && pg_ctlcluster --skip-systemctl-redirect $$(ls /etc/postgresql | head -1) main start || true; \
	fi

# The turntable scenes are meshes on a floor: the demo's bunny is read from the shared data
# (../shared/data/meshes); without it the demo stops before simulating, saying so (the analytic
# spheres scene has no turntable).
DEMO_SCENE := bunny
DEMO_MESH := ../shared/data/meshes/stanford-bunny.obj

# The whole-object path, embedded (no server): a realistic simulated turntable set (plate,
# turntable base, table and backdrop in view, no roi), merged, its textured Thumb and Low
# derivatives, published for Voyager with paradata and a QA report, tiled and previewed.
# 8 views at 640x480 keep it near a minute after set-up (see README: the figures).
DEMO_VIEWS := 8
DEMO_SIZE := 640x480

demo: setup
	@test -f $(DEMO_MESH) || { echo "make demo: the turntable scene needs $(DEMO_MESH) (the shared data, see README), not found"; exit 2; }
	@rm -rf demo && mkdir -p demo
	$(BIN)/graylight simulate --scene $(DEMO_SCENE) --views $(DEMO_VIEWS) --turntable --size $(DEMO_SIZE) --projector 512x384 --out demo/set
	$(BIN)/graylight merge demo/set --out demo/merge
	$(BIN)/graylight derivatives demo/merge --levels thumb,low
	$(BIN)/graylight publish demo/merge --out demo/published --title "$(DEMO_SCENE) (simulated turntable scan)" --collection "Graylight demo" --identifier demo-0001
	$(BIN)/graylight tiles demo/merge/merged.ply --out demo/merge/tiles
	$(BIN)/graylight preview demo/merge/tiles --merge demo/merge --out demo/preview.mp4 --seconds 4
	@echo
	@echo "Demo finished ($(DEMO_SCENE) on a turntable, $(DEMO_VIEWS) views, embedded mode, no server):"
	@echo "  scan set (views, rig, true poses)        demo/set/"
	@echo "  registered, fused and meshed object      demo/merge/ (merged.ply, mesh.glb, registration.json)"
	@echo "  textured derivatives (Thumb, Low)        demo/merge/mesh_thumb.glb, mesh_low.glb, derivatives.json"
	@echo "  Voyager scene, paradata, quality report  demo/published/ (scene.svx.json, paradata.json, qa.html)"
	@echo "  preview flythrough (textured, axis up)   demo/preview.mp4, demo/preview.png"
	@echo "  verdict: $$($(BIN)/python -c 'import json; print(json.load(open("demo/published/qa.json"))["verdict"]["line"])')"
	@echo
	@echo "Open it in the viewer:  $(BIN)/graylight view demo/merge"

test: setup services
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) --dist loadgroup -q tests

test-fast: setup services
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) --dist loadgroup -q -m "not slow" tests

bench: setup services
	$(BIN)/python -m tests.bench.run

lint: setup
	$(BIN)/ruff check .

clean:
	rm -rf demo .pytest_cache
