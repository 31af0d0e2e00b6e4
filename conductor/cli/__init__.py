"""The ``twin`` command line (:func:`conductor.cli.main.main`)."""
