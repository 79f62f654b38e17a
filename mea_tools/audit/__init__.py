"""`mea audit`: the physics audit of augmented episodes as a report (options ``config``, the general
tasks' audit ``general``, Surgical Grasp Any's ``surgical``, the tables ``tables``). The replay it
reports on is the augmenter's own library (``services.augmenter.audit_*``), which the augmenter
service also runs on live copies."""
