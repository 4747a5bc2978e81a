"""``python -m scg_jax``: the ``scg-jax`` command line."""

import sys

from scg_jax.cli import main

if __name__ == "__main__":
    sys.exit(main())
