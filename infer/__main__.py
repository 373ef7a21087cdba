"""``python -m infer``: see :mod:`infer.cli`."""

from infer.cli import main

if __name__ == "__main__":
    main()
