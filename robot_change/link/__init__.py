"""The serial link to the base controller: the wire format (sans-IO) and the session.

Modules are imported by their full path (the public API is the package face,
:mod:`robot_change`)."""
