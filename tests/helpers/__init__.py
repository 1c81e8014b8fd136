"""Helpers the tests share: data makers, paths, subprocess runs."""
