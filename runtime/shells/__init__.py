"""The command-line shells: `tensortouch` and its deploy subcommands.
"""
