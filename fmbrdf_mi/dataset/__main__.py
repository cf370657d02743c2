"""``python -m fmbrdf_mi.dataset --config CONFIG --out DIR`` (= ``fmbrdf-mi dataset``)."""
import sys

from .command import main

sys.exit(main())
