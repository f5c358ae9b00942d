"""The ``label-tool`` command line (the review tool is not in this version yet)."""
import sys


def main(argv=None) -> int:
    print("label-tool: not yet available in this version (review GUI, pre-flags and manifests are coming)",
          file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
