"""The fleet: every robot's checks, changes and health on an MQTT broker (paho-mqtt).

A transport, like :mod:`robot_change.link`: it takes JSON-ready dictionaries and publishes
them, and imports nothing of the numeric layers (cloud, mixture, change) nor of the link; the
service (:mod:`robot_change.service`) wires it to the daemon.

    connection  BrokerSettings (a checked broker URL, TLS files, user name + password file),
                a configured paho client, what a refused connection means
    topics      the topic names and the JSON messages (envelopes around the daemon's own
                check report; status; read-only requests)
    spool       the bounded on-disk spool (atomic files, oldest dropped and counted)
    publisher   Publisher: a bounded queue, a writer thread (-> spool) and a network thread
                (spool -> broker in order, QoS 1; the retained status and its Last Will)
    receiver    Receiver: the subscribing side (fleet-tail, dashboards), duplicates dropped by
                report id

Modules are imported by their full path.
"""
