"""The ``weathergen`` command line (installed as ``weathergen.cli``)."""
