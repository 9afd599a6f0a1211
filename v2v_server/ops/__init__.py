"""Configuration and operations: settings declared once (flags, YAML, docs), the recipe and
serving settings, the v2v-serve and v2v-keygen commands, metrics and logs."""
