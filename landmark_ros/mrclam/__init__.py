"""Replay of the UTIAS MRCLAM datasets through the pipeline and the nodes."""
