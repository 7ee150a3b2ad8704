"""`cubecloud cohort`: the pipeline over many scans on a workflow engine, and the paired statistics."""
