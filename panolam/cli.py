"""The ``panolam`` command line (training, inference and evaluation are not in this version yet)."""
import sys


def main(argv=None) -> int:
    print("panolam: not yet available in this version (train, infer and eval are coming)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
