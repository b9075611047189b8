"""The transport: Zenoh sessions, key expressions and message codecs. Knows nothing of physics."""
