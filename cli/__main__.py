"""``python -m weathergen.cli ARGS``: the command line without the ``weathergen`` script (a source
checkout, a notebook's ``!python -m ...``)."""

from .main import main

if __name__ == "__main__":
    main()
