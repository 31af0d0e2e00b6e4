import sys

try:
    from .main import main
except KeyboardInterrupt:  # Ctrl-C while the command's modules load: nothing began, nothing to summarise
    print("twin: stopped by Ctrl-C while starting: nothing ran", file=sys.stderr)
    sys.exit(130)

sys.exit(main())
