"""`python -m marlmerge` runs the command-line interface."""

from marlmerge.cli import main

raise SystemExit(main())
