"""The train stage (SPEC §2): a Lightning perception map per dataset recipe (`python -m pipeline.train`).

The network, loading a map and inference live below every stage, in :mod:`pipeline.perception`.
"""
