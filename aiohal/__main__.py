import sys

try:
    from .cli import main

    status = main()
except KeyboardInterrupt:  # Ctrl-C while the modules load, before the CLI handles signals
    status = 130
sys.exit(status)
