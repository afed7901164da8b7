//! Address ranges in CIDR notation (`192.168.1.0/24`, `fd00::/8`, a bare address for one host),
//! for allow-lists such as a VMC input's `from=` (`--vmc-in`).

use std::fmt;
use std::net::IpAddr;
use std::str::FromStr;

/// Why a CIDR did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CidrError {
    /// The part before `/` is not an IPv4 or IPv6 address.
    #[error("{text:?} is not an IPv4 or IPv6 address (e.g. 192.168.1.0/24, fd00::/8, 10.0.0.7)")]
    NotAnAddress {
        /// What was given.
        text: String,
    },
    /// The part after `/` is not a number.
    #[error("{text:?}: the prefix length after '/' must be a number")]
    BadPrefix {
        /// What was given.
        text: String,
    },
    /// The prefix is longer than the address (32 for IPv4, 128 for IPv6).
    #[error("{text:?}: a prefix length of {prefix} is more than the address's {max} bits")]
    PrefixTooLong {
        /// What was given.
        text: String,
        /// Its prefix length.
        prefix: u32,
        /// The address's bits.
        max: u32,
    },
    /// Bits below the prefix are set: almost always a typo of the network meant.
    #[error("{text:?} has bits set below its /{prefix}: did you mean {network}/{prefix}?")]
    HostBits {
        /// What was given.
        text: String,
        /// Its prefix length.
        prefix: u8,
        /// The network it probably meant.
        network: IpAddr,
    },
}

/// A range of addresses: a network address and how many leading bits of it a member shares.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cidr {
    network: IpAddr,
    prefix: u8,
}

impl Cidr {
    /// Whether `ip` is in the range. An IPv4-mapped IPv6 address (`::ffff:a.b.c.d`, what a
    /// dual-stack socket reports for an IPv4 sender) counts as its IPv4 address.
    #[must_use]
    pub fn contains(&self, ip: IpAddr) -> bool {
        match (self.network, ip.to_canonical()) {
            (IpAddr::V4(net), IpAddr::V4(ip)) => {
                masked(u128::from(u32::from(ip)), 32, self.prefix) == u128::from(u32::from(net))
            }
            (IpAddr::V6(net), IpAddr::V6(ip)) => {
                masked(u128::from(ip), 128, self.prefix) == u128::from(net)
            }
            _ => false,
        }
    }

    /// The network address.
    #[must_use]
    pub fn network(&self) -> IpAddr {
        self.network
    }

    /// The prefix length in bits.
    #[must_use]
    pub fn prefix(&self) -> u8 {
        self.prefix
    }
}

/// `bits` (an address `width` bits wide) with every bit below the first `prefix` cleared.
fn masked(bits: u128, width: u32, prefix: u8) -> u128 {
    let keep = u32::from(prefix).min(width);
    if keep == 0 {
        return 0;
    }
    let mask = (u128::MAX << (width - keep)) & (u128::MAX >> (128 - width));
    bits & mask
}

impl FromStr for Cidr {
    type Err = CidrError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let text = s.trim();
        let (addr, prefix) = match text.split_once('/') {
            Some((a, p)) => (a, Some(p)),
            None => (text, None),
        };
        let address: IpAddr = addr.parse().map_err(|_| CidrError::NotAnAddress {
            text: addr.to_owned(),
        })?;
        let max: u32 = if address.is_ipv4() { 32 } else { 128 };
        let prefix = match prefix {
            None => max,
            Some(p) => p.parse::<u32>().map_err(|_| CidrError::BadPrefix {
                text: text.to_owned(),
            })?,
        };
        if prefix > max {
            return Err(CidrError::PrefixTooLong {
                text: text.to_owned(),
                prefix,
                max,
            });
        }
        // `prefix` ≤ 128 here.
        let prefix = u8::try_from(prefix).unwrap_or(128);
        let network = match address {
            IpAddr::V4(a) => {
                let bits = masked(u128::from(u32::from(a)), 32, prefix);
                IpAddr::V4(u32::try_from(bits).unwrap_or(0).into())
            }
            IpAddr::V6(a) => IpAddr::V6(masked(u128::from(a), 128, prefix).into()),
        };
        if network != address {
            return Err(CidrError::HostBits {
                text: text.to_owned(),
                prefix,
                network,
            });
        }
        Ok(Self { network, prefix })
    }
}

impl fmt::Display for Cidr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.network, self.prefix)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn ipv4_ranges_hold_their_members_only() {
        let lan: Cidr = "192.168.1.0/24".parse().unwrap();
        assert!(lan.contains(ip("192.168.1.0")));
        assert!(lan.contains(ip("192.168.1.255")));
        assert!(!lan.contains(ip("192.168.2.1")));
        assert!(!lan.contains(ip("192.168.0.255")));
        // What a dual-stack socket reports for an IPv4 sender.
        assert!(lan.contains(ip("::ffff:192.168.1.7")));
        assert!(!lan.contains(ip("fe80::1")));
        let host: Cidr = "127.0.0.1".parse().unwrap();
        assert_eq!(host.to_string(), "127.0.0.1/32");
        assert!(host.contains(ip("127.0.0.1")));
        assert!(!host.contains(ip("127.0.0.2")));
        let all: Cidr = "0.0.0.0/0".parse().unwrap();
        assert!(all.contains(ip("203.0.113.9")));
        assert!(!all.contains(ip("::1")));
        let odd: Cidr = "10.0.0.128/25".parse().unwrap();
        assert!(odd.contains(ip("10.0.0.200")));
        assert!(!odd.contains(ip("10.0.0.127")));
    }

    #[test]
    fn ipv6_ranges_hold_their_members_only() {
        let ula: Cidr = "fd00::/8".parse().unwrap();
        assert!(ula.contains(ip("fd12:3456::1")));
        assert!(!ula.contains(ip("fe80::1")));
        assert!(!ula.contains(ip("10.0.0.1")));
        let host: Cidr = "::1".parse().unwrap();
        assert_eq!(host.prefix(), 128);
        assert!(host.contains(ip("::1")));
        assert!(!host.contains(ip("::2")));
        let net: Cidr = "2001:db8:1:2::/64".parse().unwrap();
        assert!(net.contains(ip("2001:db8:1:2:ffff:ffff:ffff:ffff")));
        assert!(!net.contains(ip("2001:db8:1:3::")));
        let all: Cidr = "::/0".parse().unwrap();
        assert!(all.contains(ip("2001:db8::1")));
    }

    #[test]
    fn bad_ranges_get_errors_that_say_what_is_wrong() {
        let cases: [(&str, CidrError); 6] = [
            (
                "192.168.1/24",
                CidrError::NotAnAddress {
                    text: "192.168.1".into(),
                },
            ),
            (
                "host.lan",
                CidrError::NotAnAddress {
                    text: "host.lan".into(),
                },
            ),
            (
                "10.0.0.0/x",
                CidrError::BadPrefix {
                    text: "10.0.0.0/x".into(),
                },
            ),
            (
                "10.0.0.0/33",
                CidrError::PrefixTooLong {
                    text: "10.0.0.0/33".into(),
                    prefix: 33,
                    max: 32,
                },
            ),
            (
                "fd00::/129",
                CidrError::PrefixTooLong {
                    text: "fd00::/129".into(),
                    prefix: 129,
                    max: 128,
                },
            ),
            (
                "192.168.1.5/24",
                CidrError::HostBits {
                    text: "192.168.1.5/24".into(),
                    prefix: 24,
                    network: ip("192.168.1.0"),
                },
            ),
        ];
        for (text, expected) in cases {
            assert_eq!(text.parse::<Cidr>().unwrap_err(), expected, "{text}");
        }
        let hint = "192.168.1.5/24".parse::<Cidr>().unwrap_err().to_string();
        assert!(hint.contains("did you mean 192.168.1.0/24"), "{hint}");
        assert!("".parse::<Cidr>().is_err());
        assert!("/8".parse::<Cidr>().is_err());
        assert!("10.0.0.0/-1".parse::<Cidr>().is_err());
    }
}
