"""ASTERIX input: decoding, captures and the bridge to the contract's payloads."""
