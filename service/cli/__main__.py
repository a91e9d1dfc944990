"""``python -m service.cli``: the ``mfgnet`` command."""

from service.cli import main

main()
