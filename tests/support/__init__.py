"""What the tests share that is not a fixture: small helpers, a headless browser, the multi-process worker, the Node
scripts of the export readers."""
