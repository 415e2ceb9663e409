"""The ``egoposevr`` console script: one entry point, one subcommand per job."""
