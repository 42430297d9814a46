// REST calls of the Flash-Mono gateway, with the API key in the X-API-Key header.

export class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

export class Api {
  constructor(apiKey = "") {
    this.apiKey = apiKey;
  }

  headers() {
    return this.apiKey ? { "X-API-Key": this.apiKey } : {};
  }

  async request(path, params = {}, init = {}) {
    const url = new URL(path, window.location.origin);
    for (const [key, value] of Object.entries(params)) {
      if (value !== undefined && value !== null) url.searchParams.set(key, String(value));
    }
    const response = await fetch(url, { ...init, headers: { ...this.headers(), ...(init.headers || {}) } });
    if (!response.ok) {
      let message = `${response.status} ${response.statusText}`;
      try {
        const body = await response.json();
        if (body && body.detail) message = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail);
      } catch (_) { /* not JSON */ }
      throw new ApiError(response.status, message);
    }
    return response;
  }

  // A page of sessions, newest first: {sessions, next_cursor}; `filters` as the API's (status, name, device_id).
  async sessions(limit = 50, cursor = null, filters = {}) {
    return (await this.request("/v1/sessions", { limit, cursor, ...filters })).json();
  }

  // A page of saved maps, newest first: {maps, next_cursor}.
  async maps(limit = 50, cursor = null) {
    return (await this.request("/v1/maps", { limit, cursor })).json();
  }

  // A saved map: its latest version's metadata, every version, and the sessions that built or used it.
  async savedMap(id) {
    return (await this.request(`/v1/maps/${encodeURIComponent(id)}`)).json();
  }

  async createSession(body) {
    const init = { method: "POST", body: JSON.stringify(body), headers: { "Content-Type": "application/json" } };
    return (await this.request("/v1/sessions", {}, init)).json();
  }

  async session(id) {
    return (await this.request(`/v1/sessions/${encodeURIComponent(id)}`)).json();
  }

  async trajectory(id, which = "all") {
    return (await this.request(`/v1/sessions/${encodeURIComponent(id)}/trajectory`, { format: "json", which })).json();
  }

  async render(id, pose, camera, kind = "color") {
    const params = { pose: pose.map((v) => v.toPrecision(9)).join(","), kind, ...camera };
    return (await this.request(`/v1/sessions/${encodeURIComponent(id)}/render`, params)).blob();
  }

  // The map file in `format` (ply, spz or splat) of a session (`kind` "sessions") or a saved map ("maps"): the
  // Response, for .blob() or .arrayBuffer().
  async map(id, format = "ply", kind = "sessions") {
    return this.request(`/v1/${kind}/${encodeURIComponent(id)}/map`, { format });
  }
}
