"""One module per CLI sub-command: each defines ``configure(parser)`` and ``run(args) -> int``."""
