"""Northbound interfaces (SPEC 11, issue 14): an MQTT publisher (Sparkplug B edge node, or plain
JSON topics) with store-and-forward in the history database, and the Prometheus health endpoint
(``edge.health``). Both are optional and off by default; neither blocks the scan loop.

Modules:

* ``config`` - the optional ``northbound:`` section of gateway.yaml (stdlib only);
* ``metrics`` - the metric table: names, data types, units, where each value comes from (stdlib);
* ``outbox`` - store-and-forward: references to unsent history rows, kept by SQLite triggers in
  the history database itself, so nothing is lost across a broker outage or a restart (stdlib);
* ``sparkplug`` - Sparkplug B payloads (the Eclipse Tahu protobuf schema, packaged by
  ``tahutils``) and ``jsonmode`` - the plain-JSON topic layout;
* ``publisher`` - the MQTT client (paho-mqtt 2.x) in its own thread.

Only ``publisher`` and ``sparkplug`` import the optional extra ``northbound`` (paho-mqtt,
tahutils); the daemon imports them only when ``northbound.mqtt.enabled`` is true.
"""
