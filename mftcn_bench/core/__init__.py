"""The run core every layer may use: errors, atomic files, provenance, identities, the home folder, spec
files and the registry of encoders and tasks."""
