import sys

try:
    from .cli import main

    code = main()
except KeyboardInterrupt:  # before the command's own handler is in place (while modules load)
    print("interrupted; no partial output file was left", file=sys.stderr)
    code = 130
sys.exit(code)
