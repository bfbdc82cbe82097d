"""Who may log in when the endpoint is secured: the users of cell.yaml (docs/contract.md §8)."""
from __future__ import annotations

import hmac
from typing import Any

from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.user_managers import UserManager

from controller.opcua.endpoint import password_hash


class PasswordUsers(UserManager):
    """Username/password users from cell.yaml (`opcua.users: {name: "sha256:…"}`); no anonymous."""

    def __init__(self, users: dict[str, str]) -> None:
        self._users = dict(users)

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if username is None or password is None or username not in self._users:
            return None
        if not hmac.compare_digest(password_hash(password), self._users[username]):
            return None
        return User(role=UserRole.User, name=username)
