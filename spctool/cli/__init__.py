"""Thin click commands: read inputs, call one stage, write artifacts."""
