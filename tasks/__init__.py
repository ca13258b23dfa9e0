"""Orchestration steps: pipeline definitions (`pipeline`, `stages`), store-cached execution
(`execute`) and their thin Prefect task wrappers (`steps`, the only module importing Prefect)."""
