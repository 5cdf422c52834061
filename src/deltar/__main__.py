"""``python -m deltar ...`` runs the ``deltar`` command."""

from deltar.cli.entry import main

main()
