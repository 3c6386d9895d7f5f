"""CLI subcommands. Each module defines ``add_parser(subparsers)`` and keeps its module-level imports to
argparse and the standard library, so that ``stagectl --help`` stays fast; heavy imports happen inside
the command's function.
"""
