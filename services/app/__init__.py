"""The application: the ``sigmaslam`` command (:mod:`.cli`), its subcommands (``*_cmd.py``, :mod:`.router`), the
supervisor that runs the processes (:mod:`.supervisor`) and what only commands use. Process packages
(``services/<process>/``) never import from here; the one exception is :mod:`.config`, a schema module
composed into :mod:`services.app.system_config`."""
