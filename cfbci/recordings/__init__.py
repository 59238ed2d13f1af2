"""Recordings' tools: re-analysis under other settings (``cfbci replay``), their
re-publication, reports and exports."""
