"""mftcn-bench: benchmark suite and evaluation harness for learned visual representations for control."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("mftcn-bench")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
