"""One run, spec -> data -> encoder -> task -> result (`runner`), and the encoder conformance check."""
