"""`python -m geer_ns.selftest`: the self-test child (geer_ns/selftest/child.py)."""

import sys

from geer_ns.selftest.child import main

sys.exit(main())
