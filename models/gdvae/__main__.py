"""`python -m gdvae`: the training kit's command line."""

from .cli import main

raise SystemExit(main())
