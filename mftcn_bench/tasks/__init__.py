"""Built-in tasks: each evaluates a frozen encoder and returns metrics."""
