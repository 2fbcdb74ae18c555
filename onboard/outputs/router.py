"""`nislam router`: a zenoh router for the fleet, through zenoh's own router
mode (the Python binding carries it), configured from `[router]`.

Vehicles and ground stations connect to it as clients (or peers); it routes
pose, status and key frames to every subscriber and queries to the vehicles'
queryables. Several routers join each other with `connect`. Nothing listens
beyond `listen`, nothing scouts (multicast and gossip off).

With TLS (`tls_root_ca`, `tls_certificate`, `tls_private_key`) the router
listens on `tls/...` endpoints only and asks every client for a certificate
signed by the fleet CA (mutual TLS). With `acl = true` (needs TLS) zenoh's
access control matches each link to a subject by its certificate's common
name and denies everything not allowed here:

    vehicle <id>   put / delete / reply / queryable / liveliness token under
                   nislam/<id>/**; it is sent queries on its keys and the
                   subscriber declarations under nislam/** (its publishers put
                   only what someone subscribes to). Nothing under another
                   vehicle's prefix, no query of its own.
    ground         subscribe and query nislam/** (every map), liveliness, and
                   its fleet status queryable on nislam/@fleet/status.

`router_json(cfg)` is the configuration as zenoh's JSON: `nislam router
--print-config` prints it, and the stock `zenohd -c FILE` runs on it
unchanged (docs/fleet.md).
"""

from __future__ import annotations

import json
import logging
import threading
from typing import Any

import zenoh

from onboard import NislamError
from onboard.outputs.settings import RouterConfig
from onboard.outputs.zenoh_session import base_config, open_session, tls_settings

log = logging.getLogger(__name__)

FLEET_STATUS_KEY = "nislam/@fleet/status"  # a verbatim chunk: `nislam/*` never matches it

# What a vehicle may send (under its own prefix), and what flows towards it
# (egress) so its own entities work: queries on its keys, and the subscriber
# declarations of the ground stations, whose key expressions (nislam/*/pose)
# are wider than its prefix: without them a client puts nothing, seeing no
# subscriber. A declaration carries a key expression only, no data.
_VEHICLE_SENDS = ["put", "delete", "reply", "declare_queryable", "liveliness_token"]
_VEHICLE_IS_SENT = ["query", "liveliness_query"]
_VEHICLE_LEARNS = ["declare_subscriber", "declare_liveliness_subscriber"]
_GROUND_DOES = ["put", "delete", "query", "reply", "declare_subscriber", "declare_queryable",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"]


def access_control(cfg: RouterConfig) -> dict[str, Any]:
    """zenoh's `access_control` section: deny by default, one subject and two
    rules per vehicle (its certificate's common name = its id), one for the
    ground stations."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for vid in cfg.vehicles:
        keys = [f"nislam/{vid}/**"]
        rules += [
            {"id": f"{vid}-sends", "permission": "allow", "flows": ["ingress"],
             "messages": _VEHICLE_SENDS, "key_exprs": keys},
            {"id": f"{vid}-is-sent", "permission": "allow", "flows": ["egress"],
             "messages": _VEHICLE_IS_SENT + _VEHICLE_SENDS, "key_exprs": keys},
        ]
        subjects.append({"id": f"vehicle-{vid}", "cert_common_names": [vid]})
        policies.append({"id": f"vehicle-{vid}",
                         "rules": [f"{vid}-sends", f"{vid}-is-sent", "vehicles-learn"],
                         "subjects": [f"vehicle-{vid}"]})
    if cfg.vehicles:
        rules.append({"id": "vehicles-learn", "permission": "allow", "flows": ["egress"],
                      "messages": _VEHICLE_LEARNS, "key_exprs": ["nislam/**"]})
    if cfg.grounds:
        rules.append({"id": "ground", "permission": "allow", "flows": ["ingress", "egress"],
                      "messages": _GROUND_DOES, "key_exprs": ["nislam/**", FLEET_STATUS_KEY]})
        subjects.append({"id": "ground", "cert_common_names": list(cfg.grounds)})
        policies.append({"id": "ground", "rules": ["ground"], "subjects": ["ground"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def router_config(cfg: RouterConfig) -> zenoh.Config:
    tls = tls_settings(cfg.tls_root_ca, cfg.tls_certificate, cfg.tls_private_key, "[router]")
    if cfg.acl and tls is None:
        raise NislamError("[router] acl = true needs TLS (tls_root_ca, tls_certificate, "
                          "tls_private_key): the rules match certificate common names")
    if tls is not None:
        plain = [ep for ep in cfg.listen if not ep.startswith("tls/")]
        if plain:
            raise NislamError(f"[router] listen holds {plain[0]!r}: with TLS the router listens "
                              f"on tls/HOST:PORT endpoints only")
    conf = base_config("router", cfg.connect, cfg.listen, False, tls)
    try:
        if tls is not None:
            conf.insert_json5("transport/link/protocols", json.dumps(["tls"]))
        if cfg.acl:
            conf.insert_json5("access_control", json.dumps(access_control(cfg)))
    except zenoh.ZError as e:
        raise NislamError(f"zenoh refused the router configuration: {e}") from None
    return conf


def router_json(cfg: RouterConfig) -> str:
    """The router's zenoh configuration as JSON (for `zenohd -c`): only the
    keys set here, the rest stays zenoh's default."""
    full = json.loads(str(router_config(cfg)))
    keep = {"mode": full["mode"], "connect": full["connect"], "listen": full["listen"],
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}
    tls = full["transport"]["link"]["tls"]
    if tls.get("root_ca_certificate"):
        keep["transport"] = {"link": {"protocols": ["tls"],
                                      "tls": {k: v for k, v in tls.items() if v is not None}}}
    if full["access_control"]["enabled"]:
        keep["access_control"] = full["access_control"]
    return json.dumps(_no_nulls(keep), indent=2)


def _no_nulls(v: Any) -> Any:
    """Without the null (unset) values: zenoh's defaults apply to those."""
    if isinstance(v, dict):
        return {k: _no_nulls(x) for k, x in v.items() if x is not None}
    if isinstance(v, list):
        return [_no_nulls(x) for x in v]
    return v


def run_router(cfg: RouterConfig, stop: threading.Event,
               on_ready: Any = None) -> None:
    """Run a router until `stop` is set."""
    session = open_session(router_config(cfg))
    try:
        log.info("router %s listening on %s", session.zid(), ", ".join(cfg.listen))
        if on_ready is not None:
            on_ready(str(session.zid()))
        stop.wait()
    finally:
        session.close()
