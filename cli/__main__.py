"""``python -m scg_cli``: the ``scg-jax`` command line."""

import sys

from scg_cli import main

if __name__ == "__main__":
    sys.exit(main())
