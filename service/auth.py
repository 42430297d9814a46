"""API keys with scopes (stream, read, admin). With no keys configured, auth is off (dev mode)."""

from __future__ import annotations

import hashlib
import hmac
import logging
from dataclasses import dataclass

from fastapi import HTTPException, Request, Security, WebSocket
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from service.settings import Settings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Principal:
    """Who is calling: `key_id` (a hash of the key, stored as a session's owner) and the key's scopes."""

    key_id: str
    scopes: frozenset[str]

    @property
    def is_admin(self) -> bool:
        return "admin" in self.scopes

    def can_read_any(self) -> bool:
        return self.is_admin or "read" in self.scopes

    def owns(self, owner_key_id: str | None) -> bool:
        return self.is_admin or (owner_key_id is not None and hmac.compare_digest(owner_key_id, self.key_id))


DEV_PRINCIPAL = Principal(key_id="dev", scopes=frozenset({"stream", "read", "admin"}))


def key_id(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()[:32]


class Authenticator:
    """Resolves the key of a request to a Principal, raising 401/403 HTTPExceptions."""

    def __init__(self, settings: Settings) -> None:
        self._keys = {key_id(k): scopes for k, scopes in settings.api_keys.items()}
        self.enabled = settings.auth_enabled
        if not self.enabled:
            log.warning("=" * 20 + " NO API KEYS CONFIGURED: AUTH IS OFF (dev mode) " + "=" * 20)

    def principal(self, key: str | None) -> Principal:
        if not self.enabled:
            return DEV_PRINCIPAL
        if not key:
            raise HTTPException(401, "missing API key: send X-API-Key or Authorization: Bearer <key>")
        kid = key_id(key)
        scopes = self._keys.get(kid)
        if scopes is None:
            raise HTTPException(401, "unknown API key")
        return Principal(kid, scopes)

    def require(self, principal: Principal, *any_of: str) -> None:
        """403 unless the principal has admin or one of `any_of`."""
        if principal.is_admin or principal.scopes & set(any_of):
            return
        raise HTTPException(403, f"this API key lacks the scope {' or '.join(any_of)}")


def request_key(request: Request | WebSocket, allow_query: bool = False) -> str | None:
    """The API key from X-API-Key, Authorization: Bearer, or (WebSocket only) ?api_key=."""
    key = request.headers.get("x-api-key")
    if key:
        return key
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip() or None
    if allow_query:
        return request.query_params.get("api_key")
    return None


_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False, description="API key (scopes stream/read/admin)")
_bearer = HTTPBearer(auto_error=False, description="the API key as a bearer token")


def caller(request: Request, api_key: str | None = Security(_api_key_header),
           bearer: HTTPAuthorizationCredentials | None = Security(_bearer)) -> Principal:
    """FastAPI dependency: the authenticated caller of an HTTP request."""
    return request.app.state.auth.principal(api_key or (bearer.credentials if bearer else None))
