"""``python -m wsim ...`` is the same as the ``wsim`` console script."""

from wsim.cli import main

raise SystemExit(main())
