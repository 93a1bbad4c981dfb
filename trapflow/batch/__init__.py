"""`trapflow process`: batch re-analysis of finite inputs on dask.distributed.

plan.py finds the inputs and cuts them into chunks (pure); chunk.py is the task a Dask
worker runs on one chunk, reading its own pairs where it runs; run.py is the client:
cluster, submission, progress, resume, per-input results, ledgers and the summary.
"""
