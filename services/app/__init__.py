"""The application: the ``sigmaslam`` command (:mod:`.cli`) and its commands, the registry of processes
(:mod:`.processes`) with the one generic process entry (:mod:`.process_cmd`), the system config
(:mod:`.system_config`), the supervisor that runs the processes (:mod:`.supervisor`) and what only commands use
(evaluations, datasets, the replica renderer, metrics). Process packages (``services/<process>/``) never import from
here: each gets its system config handed over by its description's ``build``."""
