"""``python -m service`` is the ``objslam`` command."""

from service.cli import main

main()
