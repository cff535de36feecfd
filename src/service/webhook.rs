//! Webhook deliveries: signed, de-duplicable, bounded, and only to targets
//! the daemon may call.
//!
//! Each delivery is a POST of the setpoint's JSON with three headers, after
//! the convention of Rachio's and Stripe's webhooks:
//!
//! * `X-Rootzone-Delivery`: a UUID, the same on every retry of one delivery,
//!   for the receiver to de-duplicate on;
//! * `X-Rootzone-Timestamp`: Unix seconds (real time, not the daemon's
//!   clock) at which this attempt was signed;
//! * `X-Rootzone-Signature`: `sha256=` and the hex HMAC-SHA256, keyed by the
//!   field's secret, of `timestamp + "." + body`.
//!
//! A receiver recomputes the HMAC, compares it in constant time and refuses
//! a timestamp more than [`REPLAY_WINDOW_S`] from its own time and a delivery
//! id it has seen ([`ReplayGuard`]).

use std::collections::{HashMap, VecDeque};
use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

use hmac::{Hmac, KeyInit, Mac};
use sha2::Sha256;
use tokio_util::sync::CancellationToken;

pub const DELIVERY_HEADER: &str = "x-rootzone-delivery";
pub const TIMESTAMP_HEADER: &str = "x-rootzone-timestamp";
pub const SIGNATURE_HEADER: &str = "x-rootzone-signature";

/// How far a signed timestamp may lie from the receiver's time [s].
pub const REPLAY_WINDOW_S: i64 = 300;

/// Attempts per delivery, and the pause before each retry.
pub const ATTEMPTS: usize = 4;
const BACKOFF: [Duration; ATTEMPTS - 1] = [
    Duration::from_secs(1),
    Duration::from_secs(2),
    Duration::from_secs(4),
];
/// Time limit of one attempt.
const ATTEMPT_TIMEOUT: Duration = Duration::from_secs(10);

type HmacSha256 = Hmac<Sha256>;

fn mac(secret: &str, timestamp: i64, body: &[u8]) -> HmacSha256 {
    // HMAC takes keys of any length
    let mut mac = HmacSha256::new_from_slice(secret.as_bytes()).expect("HMAC accepts any key");
    mac.update(timestamp.to_string().as_bytes());
    mac.update(b".");
    mac.update(body);
    mac
}

/// The `X-Rootzone-Signature` value of `body` signed at `timestamp`.
pub fn sign(secret: &str, timestamp: i64, body: &[u8]) -> String {
    format!(
        "sha256={}",
        hex::encode(mac(secret, timestamp, body).finalize().into_bytes())
    )
}

/// Checks a delivery's signature and its timestamp against `now` (Unix
/// seconds).
pub fn verify(
    secret: &str,
    timestamp: &str,
    signature: &str,
    body: &[u8],
    now: i64,
) -> Result<(), String> {
    let t: i64 = timestamp
        .trim()
        .parse()
        .map_err(|_| format!("{TIMESTAMP_HEADER} '{timestamp}' is not Unix seconds"))?;
    if (now - t).abs() > REPLAY_WINDOW_S {
        return Err(format!(
            "{TIMESTAMP_HEADER} {t} is {} s from now: outside the {REPLAY_WINDOW_S}-s window",
            now - t
        ));
    }
    let hex_part = signature
        .trim()
        .strip_prefix("sha256=")
        .ok_or_else(|| format!("{SIGNATURE_HEADER} must start with 'sha256='"))?;
    let given = hex::decode(hex_part).map_err(|_| format!("{SIGNATURE_HEADER} is not hex"))?;
    mac(secret, t, body)
        .verify_slice(&given)
        .map_err(|_| "the signature does not match".to_string())
}

/// Remembers the delivery ids seen within the replay window, so a replayed
/// delivery is refused; bounded in size (the oldest are forgotten first).
#[derive(Debug, Default)]
pub struct ReplayGuard {
    seen: HashMap<String, i64>,
    order: VecDeque<(i64, String)>,
}

impl ReplayGuard {
    /// Most ids kept.
    pub const CAPACITY: usize = 10_000;

    /// Records `id` seen at `now`; false if it was seen within the window.
    pub fn first_time(&mut self, id: &str, now: i64) -> bool {
        while let Some((t, old)) = self.order.front() {
            if now - t > 2 * REPLAY_WINDOW_S || self.order.len() >= Self::CAPACITY {
                self.seen.remove(old);
                self.order.pop_front();
            } else {
                break;
            }
        }
        if self.seen.contains_key(id) {
            return false;
        }
        self.seen.insert(id.to_string(), now);
        self.order.push_back((now, id.to_string()));
        true
    }
}

/// Whether the daemon refuses to call `ip` (unless the setting
/// `webhooks.allow_link_local` allows it): link-local addresses (which hold
/// the cloud metadata services, 169.254.169.254 and fd00:ec2::254), the
/// Alibaba metadata address 100.100.100.200, unspecified, broadcast and
/// multicast addresses.
pub fn forbidden(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(v4) => {
            v4.is_link_local()
                || v4.is_unspecified()
                || v4.is_broadcast()
                || v4.is_multicast()
                || v4.octets()[0] == 0
                || v4 == std::net::Ipv4Addr::new(100, 100, 100, 200)
        }
        IpAddr::V6(v6) => {
            if let Some(v4) = v6.to_ipv4_mapped() {
                return forbidden(IpAddr::V4(v4));
            }
            let first = v6.segments()[0];
            (first & 0xffc0) == 0xfe80
                || v6.is_unspecified()
                || v6.is_multicast()
                || v6 == "fd00:ec2::254".parse::<std::net::Ipv6Addr>().unwrap_or(v6)
        }
    }
}

/// Refuses, when the field is created, a webhook URL whose host is a
/// literal address the daemon does not call (names are checked at each
/// delivery, after resolution).
pub fn check_literal_target(url: &str, allow_link_local: bool) -> Result<(), String> {
    let Ok(parsed) = reqwest::Url::parse(url) else {
        return Ok(());
    };
    let ip = match parsed.host() {
        Some(url::Host::Ipv4(v4)) => IpAddr::V4(v4),
        Some(url::Host::Ipv6(v6)) => IpAddr::V6(v6),
        _ => return Ok(()),
    };
    if !allow_link_local && forbidden(ip) {
        return Err(format!(
            "actuator.url points at {ip}, a link-local, metadata or unspecified address the \
             daemon does not call (setting webhooks.allow_link_local allows it)"
        ));
    }
    Ok(())
}

/// Resolves `url`'s host and checks every address; returns the host and the
/// addresses to connect to (pinned, so a second resolution cannot point the
/// request elsewhere).
pub async fn resolve_target(
    url: &reqwest::Url,
    allow_link_local: bool,
) -> Result<(String, Vec<SocketAddr>), String> {
    let host = url.host_str().ok_or("the URL has no host")?.to_string();
    let port = url.port_or_known_default().unwrap_or(80);
    let bare = host.trim_start_matches('[').trim_end_matches(']');
    let addrs: Vec<SocketAddr> = match bare.parse::<IpAddr>() {
        Ok(ip) => vec![SocketAddr::new(ip, port)],
        Err(_) => tokio::net::lookup_host((bare, port))
            .await
            .map_err(|e| format!("cannot resolve '{host}': {e}"))?
            .collect(),
    };
    if addrs.is_empty() {
        return Err(format!("'{host}' resolves to no address"));
    }
    if !allow_link_local && let Some(bad) = addrs.iter().find(|a| forbidden(a.ip())) {
        return Err(format!(
            "'{host}' resolves to {}, a link-local or metadata address the daemon does not call \
             (setting webhooks.allow_link_local)",
            bad.ip()
        ));
    }
    Ok((host, addrs))
}

/// Delivers `body` to `url`, signed with `secret`: up to [`ATTEMPTS`]
/// attempts 1, 2 and 4 s apart, each within 10 s, stopping at once when
/// `cancel` fires (shutdown). Returns whether it was acknowledged (2xx).
pub async fn deliver(
    url: &str,
    secret: Option<&str>,
    body: Vec<u8>,
    allow_link_local: bool,
    cancel: &CancellationToken,
) -> bool {
    let delivery = uuid::Uuid::new_v4().to_string();
    let span = tracing::info_span!("webhook", delivery = %delivery);
    let _enter = span.enter();
    let parsed = match reqwest::Url::parse(url) {
        Ok(u) => u,
        Err(e) => {
            tracing::warn!(error = %e, "webhook URL is not valid; not delivered");
            return false;
        }
    };
    for attempt in 0..ATTEMPTS {
        let outcome = tokio::select! {
            _ = cancel.cancelled() => {
                tracing::info!(attempt = attempt + 1, "shutdown: webhook delivery abandoned");
                return false;
            }
            r = attempt_once(&parsed, secret, &body, &delivery, allow_link_local) => r,
        };
        match outcome {
            Ok(()) => {
                tracing::info!(attempt = attempt + 1, "webhook delivered");
                return true;
            }
            Err(Refusal::Final(e)) => {
                tracing::warn!(error = %e, "webhook not delivered");
                return false;
            }
            Err(Refusal::Retry(e)) => {
                tracing::warn!(error = %e, attempt = attempt + 1, "webhook attempt failed");
            }
        }
        if let Some(pause) = BACKOFF.get(attempt) {
            tokio::select! {
                _ = cancel.cancelled() => {
                    tracing::info!("shutdown: webhook retries abandoned");
                    return false;
                }
                _ = tokio::time::sleep(*pause) => {}
            }
        }
    }
    tracing::warn!("webhook not delivered after {ATTEMPTS} attempts");
    false
}

enum Refusal {
    /// Worth another attempt (network, 5xx, 429).
    Retry(String),
    /// Not worth one (a refused target, a 4xx).
    Final(String),
}

async fn attempt_once(
    url: &reqwest::Url,
    secret: Option<&str>,
    body: &[u8],
    delivery: &str,
    allow_link_local: bool,
) -> Result<(), Refusal> {
    // a name that does not resolve may resolve later; a forbidden address
    // will not change
    let (host, addrs) = resolve_target(url, allow_link_local).await.map_err(|e| {
        if e.contains("does not call") {
            Refusal::Final(e)
        } else {
            Refusal::Retry(e)
        }
    })?;
    super::install_tls();
    let client = reqwest::Client::builder()
        .timeout(ATTEMPT_TIMEOUT)
        .redirect(reqwest::redirect::Policy::none())
        .resolve_to_addrs(&host, &addrs)
        .build()
        .map_err(|e| Refusal::Final(format!("HTTP client: {e}")))?;
    let timestamp = chrono::Utc::now().timestamp();
    let mut request = client
        .post(url.clone())
        .header(reqwest::header::CONTENT_TYPE, "application/json")
        .header(DELIVERY_HEADER, delivery)
        .header(TIMESTAMP_HEADER, timestamp.to_string())
        .body(body.to_vec());
    if let Some(secret) = secret {
        request = request.header(SIGNATURE_HEADER, sign(secret, timestamp, body));
    }
    match request.send().await {
        Ok(r) if r.status().is_success() => Ok(()),
        Ok(r) if r.status().is_server_error() || r.status().as_u16() == 429 => {
            Err(Refusal::Retry(format!("HTTP {}", r.status())))
        }
        Ok(r) => Err(Refusal::Final(format!("HTTP {}", r.status()))),
        Err(e) => Err(Refusal::Retry(e.to_string())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_signature_verifies_and_any_change_breaks_it() {
        let body = br#"{"rate":1e-6}"#;
        let sig = sign("field-secret-0123456789", 1_700_000_000, body);
        assert!(
            verify(
                "field-secret-0123456789",
                "1700000000",
                &sig,
                body,
                1_700_000_100
            )
            .is_ok()
        );
        // another body, secret, timestamp, or a stale one
        assert!(
            verify(
                "field-secret-0123456789",
                "1700000000",
                &sig,
                b"{}",
                1_700_000_000
            )
            .is_err()
        );
        assert!(
            verify(
                "another-secret-0123456",
                "1700000000",
                &sig,
                body,
                1_700_000_000
            )
            .is_err()
        );
        assert!(
            verify(
                "field-secret-0123456789",
                "1700000001",
                &sig,
                body,
                1_700_000_000
            )
            .is_err()
        );
        let err = verify(
            "field-secret-0123456789",
            "1700000000",
            &sig,
            body,
            1_700_000_301,
        );
        assert!(err.unwrap_err().contains("window"));
    }

    #[test]
    fn the_signature_is_hmac_sha256_of_timestamp_dot_body() {
        // the MAC itself against RFC 4231, test case 2
        let mut m = HmacSha256::new_from_slice(b"Jefe").unwrap();
        m.update(b"what do ya want for nothing?");
        assert_eq!(
            hex::encode(m.finalize().into_bytes()),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
        // and the header is that MAC over "<timestamp>.<body>"
        let mut m = HmacSha256::new_from_slice(b"k").unwrap();
        m.update(b"42.{}");
        assert_eq!(
            sign("k", 42, b"{}"),
            format!("sha256={}", hex::encode(m.finalize().into_bytes()))
        );
    }

    #[test]
    fn a_replayed_delivery_id_is_refused_within_the_window() {
        let mut guard = ReplayGuard::default();
        assert!(guard.first_time("a", 0));
        assert!(!guard.first_time("a", 10));
        assert!(guard.first_time("b", 10));
        // long after the window the id has been forgotten
        assert!(guard.first_time("a", 10 + 3 * REPLAY_WINDOW_S));
    }

    #[test]
    fn link_local_and_metadata_addresses_are_forbidden() {
        for bad in [
            "169.254.169.254",
            "169.254.1.1",
            "0.0.0.0",
            "100.100.100.200",
            "224.0.0.1",
            "fe80::1",
            "fd00:ec2::254",
            "::ffff:169.254.169.254",
            "::",
        ] {
            assert!(forbidden(bad.parse().unwrap()), "{bad}");
        }
        for good in ["127.0.0.1", "10.0.0.5", "192.168.1.20", "8.8.8.8", "::1"] {
            assert!(!forbidden(good.parse().unwrap()), "{good}");
        }
    }
}

#[cfg(test)]
mod tls_tests {
    use super::*;
    use std::io::Read;

    #[tokio::test]
    async fn https_targets_get_a_tls_handshake() {
        // a plain TCP server: it sees what the client sends first, then
        // closes; a client without TLS would not connect at all
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let server = std::thread::spawn(move || {
            let (mut stream, _) = listener.accept().unwrap();
            let mut first = [0u8; 1];
            stream.read_exact(&mut first).unwrap();
            first[0]
        });
        let url = reqwest::Url::parse(&format!("https://127.0.0.1:{port}/hook")).unwrap();
        let outcome = attempt_once(&url, Some("secret-0123456789"), b"{}", "id", false).await;
        assert!(matches!(outcome, Err(Refusal::Retry(_))));
        // 0x16: a TLS handshake record (the ClientHello)
        assert_eq!(server.join().unwrap(), 0x16);
    }
}
