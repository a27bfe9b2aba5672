"""An example third-party encoder package for mftcn-bench."""
