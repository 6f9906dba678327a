"""``python -m lodscape``: the command line."""

from lodscape.cli import main

main()
