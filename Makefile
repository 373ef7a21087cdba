# The two commands of the README:  make demo  (install + main job)  and  make test  (install + tests).
PY := .venv/bin/python
STAMP := .venv/.installed

.PHONY: install test demo bench clean

$(STAMP): pyproject.toml scripts/install.sh
	bash scripts/install.sh
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadscope --no-loadscope-reorder -q tests

demo: $(STAMP)
	$(PY) -m demo

# Every benchmark on its defaults; bench/heldout.py needs a dataset and trained runs (docs/benchmarks.md,
# "Refinement on held-out scenes") and bench/flops.py is their shared helper module.
bench: $(STAMP)
	for f in bench/*.py; do \
		case $$f in bench/flops.py|bench/heldout.py) continue;; esac; \
		$(PY) $$f || exit 1; \
	done

clean:
	rm -rf .venv build *.egg-info .pytest_cache
