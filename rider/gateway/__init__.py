"""The plant gateway (`rider gateway`): every machine it sees, in OPC UA for SCADA and in
Prometheus for operations; a Zenoh peer like any Rider, never inside the daemon (docs/plant.md)."""
