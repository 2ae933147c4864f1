"""The ``posecell`` command line; the verbs and the entry point are in :mod:`service.cli.main`."""
