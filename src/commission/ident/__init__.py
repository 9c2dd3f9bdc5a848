"""The hybrid identifier: pure functions on arrays, no I/O, nothing from drive or mcaplog."""
