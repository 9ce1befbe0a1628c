"""Pydantic models for configuration and messages; JSON Schemas are generated from them."""
