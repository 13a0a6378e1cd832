"""Stops a pymodbus helper on a pymodbus it was not written for, saying why.

The helpers are written against pymodbus 3.0 (Debian 12's python3-pymodbus): its API moved in
later 3.x releases (framers, `unit=`/`slave=`). A message beats an ImportError further on.
"""

import sys

try:
    import pymodbus
except ImportError:
    sys.exit("pymodbus is missing: apt-get install python3-pymodbus")
if not pymodbus.__version__.startswith("3.0."):
    sys.exit(
        "these interop tests are written against pymodbus 3.0 (Debian 12's python3-pymodbus); "
        f"this is {pymodbus.__version__}"
    )
