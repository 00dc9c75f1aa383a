# The two commands a new user needs: `make demo` and `make test`. Both bootstrap what they need.
VENV ?= .venv
PYTHON ?= python3
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out/demo

.PHONY: demo test lint bench accuracy measurements proto lock web-vendor clean

$(STAMP): pyproject.toml constraints.txt scripts/bootstrap.sh
	VENV=$(VENV) PYTHON=$(PYTHON) scripts/bootstrap.sh

demo: $(STAMP)
	$(BIN)/arcloud demo --out $(OUT)

# Lint and types first: ruff (formatting, then its rules) on src, tests and bench; mypy on src (strict on core, ports,
# stores, client: pyproject.toml); and every `type: ignore` / `noqa` says why after it (`  # why`, or `noqa: X - why`).
lint: $(STAMP)
	$(BIN)/ruff format --check src tests bench
	$(BIN)/ruff check src tests bench
	$(BIN)/mypy
	@if grep -rnE --include='*.py' '# (type: ignore(\[[^]]*\])?|noqa(: [A-Z0-9, ]+)?) *$$' src tests bench; then \
		echo "lint: the type: ignore / noqa above gives no reason" >&2; exit 1; fi

# The suite in two runs. First every test but those tests/serial_tests.py names, on TEST_WORKERS processes
# (pytest-xdist; --dist loadfile keeps a module's tests on one process, so that its module-scoped fixtures, a
# simulated walk of 50 s among them, are built once; modules in file order, the long accuracy suites first). Then
# those alone, one at a time: they time something against a wall-clock bound. Both always run, and the target fails
# if either failed. PYTEST_ARGS goes to both, -m included (the split is tests/conftest.py's --serial option, not a
# -m); a selection that leaves one of them nothing to run is fine (pytest's exit 5), one that leaves both is not.
TEST_WORKERS ?= 2
test: $(STAMP) lint
	@{ command -v redis-server && command -v chromium; } >/dev/null 2>&1 || VENV=$(VENV) PYTHON=$(PYTHON) scripts/bootstrap.sh --test
	parallel=0; alone=0; \
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --serial skip $(PYTEST_ARGS) || parallel=$$?; \
	$(BIN)/python -m pytest --serial only $(PYTEST_ARGS) || alone=$$?; \
	if [ $$parallel = 5 ] && [ $$alone = 5 ]; then exit 5; fi; \
	for rc in $$parallel $$alone; do if [ $$rc != 0 ] && [ $$rc != 5 ]; then exit $$rc; fi; done

# Every benchmark -> bench/results/*.json (about 30 min, and bench_scaling 549 s on 2 loaded cores; accuracy apart).
# A run the docs quote is kept in a dated subfolder of bench/results and named in bench/measurements.py.
bench: $(STAMP)
	$(BIN)/python bench/bench_step.py
	$(BIN)/python bench/bench_detector.py
	$(BIN)/python bench/bench_batch.py
	$(BIN)/python bench/bench_service.py
	$(BIN)/python bench/bench_throughput.py
	$(BIN)/python bench/bench_load.py
	$(BIN)/python bench/bench_load.py --devices 100 --rate 0.42 --out bench/results/load_70.json
	$(BIN)/python bench/bench_flood.py
	$(BIN)/python bench/bench_shards.py
	$(BIN)/python bench/bench_shards.py --detector-wait-ms 300 --replay-runs 0 --out bench/results/shards_wait.json
	$(BIN)/python bench/bench_memory.py
	$(BIN)/python bench/bench_scaling.py
	$(BIN)/python bench/scaling_model.py

# Accuracy suites (simulated rooms, ScanNet renders, 7-Scenes, the HoloLens office) -> bench/results/accuracy.json; about 30 min.
# ACCURACY_ARGS=--quick for the short versions, --suites sim for one suite.
accuracy: $(STAMP)
	$(BIN)/python bench/bench_accuracy.py $(ACCURACY_ARGS)

# README.md's and docs/measurements.md's measured tables, from the results files kept in bench/results/<dated folder>
measurements: $(STAMP)
	$(BIN)/python bench/measurements.py

proto: $(STAMP)
	$(BIN)/python -m grpc_tools.protoc -Iproto --python_out=src/arcloud/proto --pyi_out=src/arcloud/proto proto/arcloud/v1/*.proto

# The browser libraries the service ships, at the versions web/package-lock.json pins, from npm, with their licences, into
# the package: three.js for the web viewer (GET /viewer), Swagger UI and ReDoc for the API docs (GET /docs, /redoc). The
# copies are committed, so that a clean checkout, the wheel and a machine offline need no npm; run this after changing a
# pin (tests/viewer and tests/service/test_service_docs.py check that the copies are of the pinned versions).
# --ignore-scripts: no package's install script runs (swagger-ui-dist's would report the install to a server).
VIEWER_VENDOR := src/arcloud/service/viewer/vendor
DOCS_VENDOR := src/arcloud/service/docs_ui
THREE := web/node_modules/three
SWAGGER_UI := web/node_modules/swagger-ui-dist
REDOC := web/node_modules/redoc
web-vendor:
	cd web && npm ci --ignore-scripts --no-audit --no-fund
	mkdir -p $(VIEWER_VENDOR) $(DOCS_VENDOR)
	cp $(THREE)/build/three.module.js $(THREE)/build/three.core.js $(THREE)/examples/jsm/controls/OrbitControls.js \
		$(THREE)/examples/jsm/renderers/CSS2DRenderer.js $(VIEWER_VENDOR)/
	cp $(THREE)/LICENSE $(VIEWER_VENDOR)/THREE-LICENSE
	cp $(SWAGGER_UI)/swagger-ui-bundle.js $(SWAGGER_UI)/swagger-ui-bundle.js.LICENSE.txt $(SWAGGER_UI)/swagger-ui.css \
		$(SWAGGER_UI)/favicon-32x32.png $(REDOC)/bundles/redoc.standalone.js $(REDOC)/bundles/redoc.standalone.js.LICENSE.txt \
		$(DOCS_VENDOR)/
	cp $(SWAGGER_UI)/LICENSE $(DOCS_VENDOR)/SWAGGER-UI-LICENSE
	cp $(SWAGGER_UI)/NOTICE $(DOCS_VENDOR)/SWAGGER-UI-NOTICE
	cp $(REDOC)/LICENSE $(DOCS_VENDOR)/REDOC-LICENSE

lock: $(STAMP)
	$(BIN)/python -m pip freeze --exclude-editable > constraints.txt

clean:
	rm -rf $(VENV) out .pytest_cache
