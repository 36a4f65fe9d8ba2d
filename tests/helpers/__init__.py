"""Helpers shared by the test modules (scenes, files in the formats the readers take, tools)."""
