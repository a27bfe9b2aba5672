"""The performance suite (`mftcn-bench bench`): speed and memory figures against their targets."""
