"""``python -m deltar ...`` runs the ``deltar`` command."""

from deltar.cli.main import main

main()
