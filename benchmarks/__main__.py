"""``python -m benchmarks``: see :mod:`benchmarks.suite`."""

from benchmarks.suite import main

if __name__ == "__main__":  # spawned worker processes import this module too: run only as the program
    main()
