"""The lsu command: launch, run, graph introspection (node, topic, service, param), doctor, demo, self-test nodes."""
