"""Configuration: the YAML schema as typed Structs, the ladder's and the modem's settings."""
