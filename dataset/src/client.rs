//! A small blocking HTTP client for the dataset server (`g2r-dataset serve`): the trainer's HTTP sample source,
//! `g2r-dataset load-test` and the tests use it. Plain HTTP only (the server binds loopback or sits behind a proxy).

use std::time::Duration;

use anyhow::{bail, Context, Result};

/// The media type of Arrow IPC streams: `/v1/shards/{name}/row-groups/{i}` and `/v1/stream` answer it.
pub const ARROW_STREAM: &str = "application/vnd.apache.arrow.stream";

/// One response, body read in full.
#[derive(Debug)]
pub struct HttpResponse {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl HttpResponse {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// Client bound to a server's base URL (`http://127.0.0.1:8080`).
#[derive(Clone)]
pub struct HttpClient {
    agent: ureq::Agent,
    base: String,
}

impl HttpClient {
    pub fn new(base_url: &str) -> Result<Self> {
        if !base_url.starts_with("http://") {
            bail!("{base_url}: only http:// URLs are supported (e.g. http://127.0.0.1:8080)");
        }
        let agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(300)))
            .build()
            .new_agent();
        Ok(Self {
            agent,
            base: base_url.trim_end_matches('/').to_string(),
        })
    }

    pub fn base_url(&self) -> &str {
        &self.base
    }

    /// GET `path` (with query), any status; transport failures are errors naming the URL.
    pub fn get(&self, path: &str, headers: &[(&str, &str)]) -> Result<HttpResponse> {
        let url = format!("{}{path}", self.base);
        let mut request = self.agent.get(&url);
        for (k, v) in headers {
            request = request.header(*k, *v);
        }
        let mut response = request.call().with_context(|| {
            format!("{url}: request failed; is `g2r-dataset serve` running there?")
        })?;
        let status = response.status().as_u16();
        let headers = response
            .headers()
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_str().unwrap_or("").to_string()))
            .collect();
        let body = response
            .body_mut()
            .with_config()
            .limit(u64::MAX)
            .read_to_vec()
            .with_context(|| format!("{url}: reading the response body"))?;
        Ok(HttpResponse {
            status,
            headers,
            body,
        })
    }

    /// GET with a 2xx status required; otherwise the server's error message becomes the error.
    pub fn get_ok(&self, path: &str, headers: &[(&str, &str)]) -> Result<HttpResponse> {
        let response = self.get(path, headers)?;
        if !(200..300).contains(&response.status) {
            bail!(
                "{}{path}: HTTP {}: {}",
                self.base,
                response.status,
                response.text().trim()
            );
        }
        Ok(response)
    }

    pub fn get_json<T: serde::de::DeserializeOwned>(&self, path: &str) -> Result<T> {
        let response = self.get_ok(path, &[])?;
        serde_json::from_slice(&response.body)
            .with_context(|| format!("{}{path}: response is not the expected JSON", self.base))
    }
}
