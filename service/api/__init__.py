"""HTTP API: schemas, dependencies, one router per resource."""
