"""Security settings of a lab network: TLS, users and access control, read from one YAML file and turned into Zenoh
configuration keys, so that every mocapflow process (router, agents, nodes, launcher, CLI clients) applies them alike.

A router uses ``tls.certificate``/``tls.key``, ``users`` and ``access``; every other process uses ``tls.ca`` and
``login``. Sections a machine does not need may be left out, so the router's private key and the list of passwords
stay on the router. Relative paths are read from the settings file's folder. See docs/lab-deployment.md.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from mocapflow.errors import MocapflowError

SECURITY_ENV = "MOCAPFLOW_SECURITY"

Action = Literal["publish", "subscribe", "query", "serve", "announce", "watch", "all"]

# What each action lets a client do, as (Zenoh message, flow seen from the router) pairs. A flow is "ingress" when
# the client sends the message to the router and "egress" when the router forwards it to the client. Publishers and
# queriers also learn where the matching subscribers and queryables are: without that a declared publisher sends
# nothing.
ACTION_MESSAGES: dict[str, tuple[tuple[str, str], ...]] = {
    "publish": (("put", "ingress"), ("delete", "ingress"), ("declare_subscriber", "egress")),
    "subscribe": (("declare_subscriber", "ingress"), ("put", "egress"), ("delete", "egress")),
    "query": (("query", "ingress"), ("reply", "egress"), ("declare_queryable", "egress")),
    "serve": (("declare_queryable", "ingress"), ("query", "egress"), ("reply", "ingress")),
    "announce": (("liveliness_token", "ingress"),),
    "watch": (("liveliness_query", "ingress"), ("declare_liveliness_subscriber", "ingress"),
              ("liveliness_token", "egress")),
}


class SecurityError(MocapflowError):
    """A security settings file is missing, malformed or names a file that does not exist."""


class TLSSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    ca: Path | None = Field(default=None, description="CA certificate (PEM) that signed the router's certificate")
    certificate: Path | None = Field(default=None, description="router: its certificate chain (PEM)")
    key: Path | None = Field(default=None, description="router: its private key (PEM)")
    verify_name: bool = Field(default=True, description="check that the router's certificate names the host joined")


class Login(BaseModel):
    model_config = ConfigDict(extra="forbid")

    user: str = Field(min_length=1)
    password: str = Field(min_length=1)


class AccessRule(BaseModel):
    model_config = ConfigDict(extra="forbid")

    users: list[str] = Field(default_factory=list, description="users the rule applies to; empty: every user")
    allow: list[Action] = Field(default_factory=list, description="what these users may do on these keys")
    deny: list[Action] = Field(default_factory=list, description="what they may not do there (wins over allow)")
    keys: list[str] = Field(default_factory=lambda: ["mocapflow/**"], min_length=1)

    @model_validator(mode="after")
    def _some_action(self) -> AccessRule:
        if not self.allow and not self.deny:
            raise ValueError("a rule needs 'allow' or 'deny' actions")
        return self


class AccessControl(BaseModel):
    model_config = ConfigDict(extra="forbid")

    default: Literal["allow", "deny"] = Field(default="deny", description="for anything no rule allows")
    rules: list[AccessRule] = Field(default_factory=list)


class SecuritySettings(BaseModel):
    """The documented settings file (``mocapflow router --config FILE``, ``--security FILE`` elsewhere)."""

    model_config = ConfigDict(extra="forbid")

    tls: TLSSettings | None = None
    login: Login | None = Field(default=None, description="the credentials this machine joins the router with")
    users: dict[str, str] = Field(default_factory=dict, description="router: accepted users and their passwords")
    access: AccessControl | None = Field(default=None, description="router: who may do what on which keys")

    @field_validator("users")
    @classmethod
    def _no_colon(cls, users: dict[str, str]) -> dict[str, str]:
        for user, password in users.items():
            if ":" in user or "\n" in user + password or not user or not password:
                raise ValueError(f"user {user!r}: names may not contain ':' and neither may be empty")
        return users

    def resolved(self, base: Path) -> SecuritySettings:
        """Certificate paths made absolute against ``base`` (the settings file's folder) and checked to exist."""
        if self.tls is None:
            return self
        paths = {}
        for name in ("ca", "certificate", "key"):
            value = getattr(self.tls, name)
            if value is not None:
                value = (base / value.expanduser()).resolve()
                if not value.is_file():
                    raise SecurityError(f"tls.{name}: {value} does not exist")
            paths[name] = value
        return self.model_copy(update={"tls": self.tls.model_copy(update=paths)})

    @property
    def tls_listener(self) -> bool:
        """True when this file lets a router listen on ``tls/`` endpoints."""
        return self.tls is not None and self.tls.certificate is not None

    def zenoh_keys(self, mode: Literal["router", "client"], users_file: Path | None = None) -> dict[str, Any]:
        """The Zenoh configuration keys these settings set for a session in ``mode``.

        A router reads its accepted users from ``users_file`` (Zenoh's ``user:password`` dictionary), written by
        ``users_dictionary``."""
        out: dict[str, Any] = {}
        tls = self.tls
        if tls is not None:
            if tls.ca is not None:
                out["transport/link/tls/root_ca_certificate"] = str(tls.ca)
            out["transport/link/tls/verify_name_on_connect"] = tls.verify_name
            if mode == "router":
                if (tls.certificate is None) != (tls.key is None):
                    raise SecurityError("tls: a router needs both 'certificate' and 'key'")
                if tls.certificate is not None:
                    out["transport/link/tls/listen_certificate"] = str(tls.certificate)
                    out["transport/link/tls/listen_private_key"] = str(tls.key)
        if mode == "client" and self.login is not None:
            out["transport/auth/usrpwd/user"] = self.login.user
            out["transport/auth/usrpwd/password"] = self.login.password
        if mode == "router":
            if self.accepted_users():
                if users_file is None:
                    raise ValueError("a router with users needs their dictionary file")
                out["transport/auth/usrpwd/dictionary_file"] = str(users_file)
            if self.access is not None:
                out["access_control"] = access_control(self.access)
        return out

    def accepted_users(self) -> dict[str, str]:
        """Users a router accepts: ``users``, and its own ``login`` so that one file serves a whole lab, including a
        launcher that starts an embedded router for its own nodes."""
        accepted = dict(self.users)
        if self.login is not None:
            accepted.setdefault(self.login.user, self.login.password)
        return accepted

    @contextmanager
    def users_dictionary(self) -> Iterator[Path | None]:
        """The accepted users as a Zenoh dictionary file, readable by this user only and deleted on exit: Zenoh
        reads it while the session opens, so no password file outlives that moment."""
        users = self.accepted_users()
        if not users:
            yield None
            return
        with tempfile.TemporaryDirectory(prefix="mocapflow-") as tmp:
            path = Path(tmp) / "users"
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write("".join(f"{user}:{password}\n" for user, password in users.items()))
            yield path


def _messages(actions: Sequence[str], flow: str) -> list[str]:
    """Zenoh messages that ``actions`` involve on ``flow``, each once."""
    chosen = list(ACTION_MESSAGES) if "all" in actions else actions
    return list(dict.fromkeys(m for a in chosen for m, f in ACTION_MESSAGES[a] if f == flow))


def access_control(access: AccessControl) -> dict[str, Any]:
    """The ``access_control`` section of a Zenoh config: per rule, one subject (its users) and one Zenoh rule per
    permission and flow, tied together by a policy."""
    rules, subjects, policies = [], [], []
    for i, rule in enumerate(access.rules):
        ids = []
        for permission, actions in (("allow", rule.allow), ("deny", rule.deny)):
            for flow in ("ingress", "egress"):
                messages = _messages(actions, flow)
                if messages:
                    ids.append(f"rule{i}-{permission}-{flow}")
                    rules.append({"id": ids[-1], "permission": permission, "flows": [flow], "messages": messages,
                                  "key_exprs": rule.keys})
        subject: dict[str, Any] = {"id": f"subject{i}"}
        if rule.users:
            subject["usernames"] = rule.users
        subjects.append(subject)
        policies.append({"id": f"policy{i}", "rules": ids, "subjects": [subject["id"]]})
    return {"enabled": True, "default_permission": access.default, "rules": rules, "subjects": subjects,
            "policies": policies}


def load_security(path: str | Path) -> SecuritySettings:
    """Read and validate a security settings file; every error names the file and the field."""
    path = Path(path).expanduser()
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except OSError as exc:
        raise SecurityError(f"{path}: cannot read: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise SecurityError(f"{path}: YAML syntax error: {exc}") from None
    try:
        settings = SecuritySettings.model_validate(raw)
    except ValidationError as exc:
        where = "; ".join(f"{'.'.join(str(p) for p in e['loc']) or 'file'}: {e['msg']}" for e in exc.errors())
        raise SecurityError(f"{path}: {where}") from None
    return settings.resolved(path.resolve().parent)


def security_path(explicit: str | Path | None = None) -> Path | None:
    """The settings file a process uses: the one it was given, else ``$MOCAPFLOW_SECURITY``, else none. Returned
    absolute so that it can be handed to worker processes started in another folder."""
    chosen = explicit or os.environ.get(SECURITY_ENV)
    return Path(chosen).expanduser().resolve() if chosen else None
