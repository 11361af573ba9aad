//! Where a webhook may point.
//!
//! A webhook makes the server send requests to a URL a client chose, so without care a
//! client could make it reach what only the server can reach: its own loopback services,
//! the cloud metadata address (169.254.169.254), the private network behind it. So a target
//! must be http(s), carry no credentials, and its host must be, and resolve only to, public
//! unicast addresses, unless the operator allows private ones (`--webhook-allow-private`)
//! or some networks (`--webhook-allow-cidr`). The check runs when a job is submitted (a 422
//! names the reason) and again at every delivery, on the addresses the connection really
//! uses ([`PolicyResolver`]), since what a name resolves to can change in between.

use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::str::FromStr;
use std::sync::Arc;
use std::time::Duration;

use reqwest::Url;
use reqwest::dns::{Addrs, Name, Resolve, Resolving};

use crate::config::WebhookArgs;

/// Longest webhook URL accepted, in bytes (the de-facto limit of browsers and proxies).
pub const MAX_URL_LEN: usize = 2048;

/// What a refusal adds, so the operator knows what to change.
const HINT: &str = "webhooks may only reach public addresses unless the server allows more \
                    (--webhook-allow-private or --webhook-allow-cidr)";

/// How long resolving a target's host may take at submission.
const RESOLVE_TIMEOUT: Duration = Duration::from_secs(5);

/// Why a target was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TargetError {
    /// Not a URL a webhook can use (scheme, credentials, length, no host).
    #[error("{0}")]
    Invalid(String),
    /// Its host is, or resolves to, an address the policy does not allow.
    #[error("{0}")]
    Refused(String),
    /// Its host does not resolve.
    #[error("{0}")]
    Unresolved(String),
}

/// A network in CIDR notation, e.g. `10.0.0.0/8` or `fd00::/8`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cidr {
    net: IpAddr,
    prefix: u8,
}

impl FromStr for Cidr {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let text = text.trim();
        let (addr, prefix) = match text.split_once('/') {
            Some((a, p)) => (a, Some(p)),
            None => (text, None),
        };
        let net: IpAddr = addr
            .parse()
            .map_err(|_| format!("{text:?} is not an IP address or CIDR network"))?;
        let max = if net.is_ipv4() { 32 } else { 128 };
        let prefix = match prefix {
            None => max,
            Some(p) => p
                .parse::<u8>()
                .ok()
                .filter(|p| *p <= max)
                .ok_or_else(|| format!("{text:?}: the prefix length must be 0 to {max}"))?,
        };
        Ok(Cidr { net, prefix })
    }
}

impl Cidr {
    pub fn contains(&self, ip: IpAddr) -> bool {
        fn masked(bits: u128, prefix: u8, width: u8) -> u128 {
            if prefix == 0 {
                0
            } else {
                bits >> (width - prefix)
            }
        }
        match (self.net, ip) {
            (IpAddr::V4(n), IpAddr::V4(a)) => {
                masked(u32::from(n).into(), self.prefix, 32)
                    == masked(u32::from(a).into(), self.prefix, 32)
            }
            (IpAddr::V6(n), IpAddr::V6(a)) => {
                masked(u128::from(n), self.prefix, 128) == masked(u128::from(a), self.prefix, 128)
            }
            _ => false,
        }
    }
}

/// Why `ip` is not a public unicast address (what kind of address it is), or `None` when
/// it is one. IPv6 addresses that embed an IPv4 address (mapped, NAT64, 6to4) are judged by
/// the IPv4 address.
pub fn non_public(ip: IpAddr) -> Option<&'static str> {
    match ip {
        IpAddr::V4(a) => non_public_v4(a),
        IpAddr::V6(a) => non_public_v6(a),
    }
}

fn non_public_v4(a: Ipv4Addr) -> Option<&'static str> {
    let [o0, o1, o2, _] = a.octets();
    Some(match () {
        _ if a.is_unspecified() || o0 == 0 => "an unspecified (\"this network\") address",
        _ if a.is_loopback() => "a loopback address",
        _ if a.is_private() => "a private address",
        _ if o0 == 100 && (o1 & 0xc0) == 64 => "a shared (carrier-grade NAT) address",
        _ if a.is_link_local() => "a link-local address",
        _ if o0 == 192 && o1 == 0 && o2 == 0 => "an IETF protocol assignment",
        _ if a.is_documentation() => "a documentation address",
        _ if o0 == 198 && (o1 & 0xfe) == 18 => "a benchmarking address",
        _ if a.is_multicast() => "a multicast address",
        _ if o0 >= 240 => "a reserved or broadcast address",
        _ => return None,
    })
}

fn non_public_v6(a: Ipv6Addr) -> Option<&'static str> {
    if let Some(v4) = a.to_ipv4_mapped() {
        return non_public_v4(v4);
    }
    let s = a.segments();
    Some(match () {
        _ if a.is_unspecified() => "an unspecified address",
        _ if a.is_loopback() => "a loopback address",
        _ if a.is_multicast() => "a multicast address",
        _ if a.is_unicast_link_local() => "a link-local address",
        _ if a.is_unique_local() => "a unique-local address",
        // fec0::/10, deprecated site-local
        _ if (s[0] & 0xffc0) == 0xfec0 => "a site-local address",
        // ::/96 (IPv4-compatible, deprecated) and 100::/64 (discard-only)
        _ if s[..6] == [0; 6] || s[..4] == [0x100, 0, 0, 0] => "a reserved address",
        _ if s[0] == 0x2001 && s[1] == 0xdb8 => "a documentation address",
        // 2001::/32 Teredo: the IPv4 client inside is obscured, so no way to judge it
        _ if s[0] == 0x2001 && s[1] == 0 => "a Teredo tunnel address",
        // 64:ff9b::/96 NAT64: judged by the IPv4 address in its last 32 bits
        _ if s[..6] == [0x64, 0xff9b, 0, 0, 0, 0] => {
            return non_public_v4(embedded_v4(s[6], s[7]));
        }
        // 2002::/16 6to4: judged by the IPv4 address in bits 16..48
        _ if s[0] == 0x2002 => return non_public_v4(embedded_v4(s[1], s[2])),
        _ => return None,
    })
}

fn embedded_v4(hi: u16, lo: u16) -> Ipv4Addr {
    Ipv4Addr::from((u32::from(hi) << 16) | u32::from(lo))
}

/// Which addresses webhooks may reach.
#[derive(Debug, Clone, Default)]
pub struct TargetPolicy {
    /// Any address at all (`--webhook-allow-private`).
    pub allow_private: bool,
    /// Non-public networks allowed all the same (`--webhook-allow-cidr`).
    pub allow: Vec<Cidr>,
}

impl TargetPolicy {
    pub fn from_args(a: &WebhookArgs) -> Result<Self, String> {
        let allow = a
            .webhook_allow_cidr
            .iter()
            .filter(|c| !c.trim().is_empty())
            .map(|c| c.parse::<Cidr>())
            .collect::<Result<_, _>>()
            .map_err(|e| format!("--webhook-allow-cidr: {e}"))?;
        Ok(Self {
            allow_private: a.webhook_allow_private,
            allow,
        })
    }

    /// `Err(what kind of address it is)` when webhooks may not reach `ip`.
    pub fn permits(&self, ip: IpAddr) -> Result<(), &'static str> {
        if self.allow_private || self.allow.iter().any(|c| c.contains(ip)) {
            return Ok(());
        }
        non_public(ip).map_or(Ok(()), Err)
    }

    /// Checks the form of a webhook URL (no network access): http or https, a host, no
    /// user name or password, at most [`MAX_URL_LEN`] bytes; an IP-literal host must also be
    /// permitted.
    pub fn check_url(&self, text: &str) -> Result<Url, TargetError> {
        if text.len() > MAX_URL_LEN {
            return Err(TargetError::Invalid(format!(
                "the URL is {} bytes long; at most {MAX_URL_LEN} are accepted",
                text.len()
            )));
        }
        let url = Url::parse(text)
            .map_err(|e| TargetError::Invalid(format!("not an absolute URL: {e}")))?;
        if !matches!(url.scheme(), "http" | "https") {
            return Err(TargetError::Invalid(format!(
                "scheme `{}` is not allowed; use http or https",
                url.scheme()
            )));
        }
        if !url.username().is_empty() || url.password().is_some() {
            return Err(TargetError::Invalid(
                "the URL must not carry a user name or password; deliveries are signed instead"
                    .into(),
            ));
        }
        if let Some(ip) = literal_ip(&url) {
            self.permits(ip)
                .map_err(|kind| TargetError::Refused(format!("{ip} is {kind}; {HINT}")))?;
        } else if url.host_str().is_none_or(str::is_empty) {
            return Err(TargetError::Invalid("the URL has no host".into()));
        }
        Ok(url)
    }

    /// [`TargetPolicy::check_url`], then resolves the host: every address it resolves to
    /// must be permitted.
    pub async fn check(&self, text: &str) -> Result<Url, TargetError> {
        let url = self.check_url(text)?;
        if literal_ip(&url).is_some() {
            return Ok(url);
        }
        let host = url.host_str().unwrap_or_default().to_string();
        let port = url.port_or_known_default().unwrap_or(80);
        let addrs = tokio::time::timeout(RESOLVE_TIMEOUT, tokio::net::lookup_host((&*host, port)))
            .await
            .map_err(|_| TargetError::Unresolved(format!("resolving {host} timed out")))?
            .map_err(|e| TargetError::Unresolved(format!("cannot resolve {host}: {e}")))?;
        let mut any = false;
        for a in addrs {
            any = true;
            self.permits(a.ip()).map_err(|kind| {
                TargetError::Refused(format!("{host} resolves to {}, {kind}; {HINT}", a.ip()))
            })?;
        }
        if !any {
            return Err(TargetError::Unresolved(format!(
                "{host} resolves to no address"
            )));
        }
        Ok(url)
    }
}

/// The host of `url` when it is an IP address.
pub fn literal_ip(url: &Url) -> Option<IpAddr> {
    // The URL parser has already normalised IPv4 forms such as `0x7f.1` to dotted quads;
    // IPv6 hosts come in brackets.
    let host = url.host_str()?;
    let bare = host
        .strip_prefix('[')
        .and_then(|h| h.strip_suffix(']'))
        .unwrap_or(host);
    bare.parse().ok()
}

/// The resolver of the delivery client: the system's, refusing a name any of whose
/// addresses the policy does not permit. The connection then goes only to addresses that
/// were checked, so a name cannot pass a check and connect somewhere else.
pub struct PolicyResolver {
    pub policy: Arc<TargetPolicy>,
}

impl Resolve for PolicyResolver {
    fn resolve(&self, name: Name) -> Resolving {
        let policy = self.policy.clone();
        let host = name.as_str().to_string();
        Box::pin(async move {
            let addrs: Vec<SocketAddr> = tokio::net::lookup_host((&*host, 0)).await?.collect();
            for a in &addrs {
                policy.permits(a.ip()).map_err(|kind| {
                    format!("refused: {host} resolves to {}, {kind}; {HINT}", a.ip())
                })?;
            }
            let addrs: Addrs = Box::new(addrs.into_iter());
            Ok(addrs)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().expect("ip")
    }

    #[test]
    fn private_loopback_link_local_and_special_addresses_are_not_public() {
        for a in [
            "0.0.0.0",
            "0.1.2.3",
            "127.0.0.1",
            "127.255.0.9",
            "10.1.2.3",
            "172.16.0.1",
            "172.31.255.255",
            "192.168.1.1",
            "100.64.0.1",
            "169.254.169.254",
            "192.0.0.8",
            "192.0.2.1",
            "198.18.0.1",
            "224.0.0.1",
            "240.0.0.1",
            "255.255.255.255",
            "::",
            "::1",
            "fe80::1",
            "fc00::1",
            "fd12:3456::1",
            "fec0::1",
            "ff02::1",
            "::ffff:127.0.0.1",
            "::ffff:10.0.0.1",
            "::ffff:169.254.169.254",
            "::127.0.0.1",
            "64:ff9b::a00:1",
            "2002:7f00:1::",
            "2001:db8::1",
            "2001:0:4136:e378::1",
        ] {
            assert!(non_public(ip(a)).is_some(), "{a} taken for public");
        }
        for a in [
            "8.8.8.8",
            "1.1.1.1",
            "172.32.0.1",
            "100.128.0.1",
            "193.0.0.1",
            "2606:4700::1111",
            "::ffff:8.8.8.8",
            "64:ff9b::808:808",
            "2002:808:808::",
        ] {
            assert_eq!(non_public(ip(a)), None, "{a} taken for non-public");
        }
    }

    #[test]
    fn cidrs_parse_and_contain() {
        let c: Cidr = "10.20.0.0/16".parse().expect("cidr");
        assert!(c.contains(ip("10.20.3.4")));
        assert!(!c.contains(ip("10.21.0.0")));
        assert!(!c.contains(ip("::ffff:10.20.3.4")));
        let c: Cidr = "fd00:1::/32".parse().expect("cidr");
        assert!(c.contains(ip("fd00:1:ffff::1")));
        assert!(!c.contains(ip("fd00:2::1")));
        let all: Cidr = "0.0.0.0/0".parse().expect("cidr");
        assert!(all.contains(ip("127.0.0.1")));
        let one: Cidr = "127.0.0.1".parse().expect("cidr");
        assert!(one.contains(ip("127.0.0.1")) && !one.contains(ip("127.0.0.2")));
        assert!("10.0.0.0/33".parse::<Cidr>().is_err());
        assert!("ten/8".parse::<Cidr>().is_err());
    }

    #[test]
    fn urls_are_checked_for_scheme_credentials_length_and_literal_addresses() {
        let strict = TargetPolicy::default();
        assert!(strict.check_url("https://8.8.8.8/hook").is_ok());
        assert!(strict.check_url("http://hooks.example/x?y=1").is_ok());
        for bad in [
            "ftp://hooks.example/x",
            "file:///etc/passwd",
            "hooks.example/x",
            "http://user:pw@hooks.example/x",
            "http://user@hooks.example/x",
        ] {
            assert!(
                matches!(strict.check_url(bad), Err(TargetError::Invalid(_))),
                "{bad} accepted"
            );
        }
        let long = format!("https://hooks.example/{}", "a".repeat(MAX_URL_LEN));
        assert!(matches!(
            strict.check_url(&long),
            Err(TargetError::Invalid(_))
        ));
        for private in [
            "http://127.0.0.1:9/x",
            "http://[::1]/x",
            "http://[::ffff:7f00:1]/x",
            "http://169.254.169.254/latest/meta-data",
            "http://10.0.0.1/x",
            "http://0.0.0.0/x",
            "http://0x7f.1/x",
            "http://2130706433/x",
        ] {
            assert!(
                matches!(strict.check_url(private), Err(TargetError::Refused(_))),
                "{private} accepted"
            );
        }
        let open = TargetPolicy {
            allow_private: true,
            allow: vec![],
        };
        assert!(open.check_url("http://127.0.0.1:9/x").is_ok());
        let some = TargetPolicy {
            allow_private: false,
            allow: vec!["10.20.0.0/16".parse().expect("cidr")],
        };
        assert!(some.check_url("http://10.20.0.5/x").is_ok());
        assert!(some.check_url("http://10.21.0.5/x").is_err());
    }

    #[tokio::test]
    async fn a_name_that_resolves_to_loopback_is_refused() {
        let strict = TargetPolicy::default();
        let e = strict.check("http://localhost:9/x").await;
        assert!(matches!(e, Err(TargetError::Refused(_))), "{e:?}");
        let resolver = PolicyResolver {
            policy: Arc::new(strict),
        };
        let name: Name = "localhost".parse().expect("name");
        let e = resolver.resolve(name).await.err().expect("refused");
        assert!(e.to_string().contains("loopback"), "{e}");
    }
}
