"""``python -m hil.bus.loopback``: serve a standalone hub (see `hil.bus.loopback.standalone`).

Key invariant: the process's exit status is `standalone.main`'s (0 clean, 2 a bad setting).
"""

from hil.bus.loopback.standalone import main

raise SystemExit(main())
