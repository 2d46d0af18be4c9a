"""``python -m weathergen ARGS``: the command line without the ``weathergen`` script, the same as
``python -m weathergen.cli``."""

from weathergen.cli.main import main

if __name__ == "__main__":
    main()
