"""`python -m neumesh_core.cli ...` (the same as the `neumesh` console script)."""
import sys

from . import main

sys.exit(main())
