"""One run, spec -> data -> encoder -> task -> result: its plan (`plan`), what it is computed from (`artifacts`,
`construct`), its record (`record`) and the orchestration of them (`runner`); moving a run between homes
(`portable`) and the encoder conformance check (`conformance`)."""
