"""Click command line of nehad: thin wrappers that parse, validate and call the library."""
