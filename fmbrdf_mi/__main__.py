"""``python -m fmbrdf_mi`` = the ``fmbrdf-mi`` command."""
from .cli import console_main

if __name__ == "__main__":
    console_main()
