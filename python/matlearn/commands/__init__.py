"""CLI subcommands: one module per command, each with `register(subparsers)` that adds its
parser and sets `func` (called with the parsed args, returns an exit code)."""
