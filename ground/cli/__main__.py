"""``python -m ground.cli``: the st16-ground command line."""

from ground.cli.main import main

raise SystemExit(main())
