//! The VMC gateway's flags: `--vmc-in [ADDR:]PORT=AVATAR[,from=CIDR,…]` and
//! `--vmc-out AVATAR=ADDR` ([`crate::vmc`]).

use super::avatar_id;
use super::cidr::Cidr;
use posecast_proto::msg::AvatarId;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::str::FromStr;

/// The configuration of one VMC input: `[ADDR:]PORT=AVATAR[,from=CIDR,…]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VmcIn {
    /// The UDP address to listen on (VMC's default port is 39539). A bare port binds to
    /// loopback: VMC has no authentication, so reaching further is the operator's choice.
    pub addr: SocketAddr,
    /// The avatar it drives.
    pub avatar: AvatarId,
    /// The senders whose datagrams are used (`from=`); empty: any sender that can reach
    /// [`Self::addr`]. Datagrams from elsewhere are dropped and counted
    /// (`posecast_vmc_packets_dropped_total{reason="sender"}`).
    pub from: Vec<Cidr>,
}

impl VmcIn {
    /// An input on `addr` driving `avatar`, open to any sender that can reach it.
    #[must_use]
    pub fn new(addr: SocketAddr, avatar: AvatarId) -> Self {
        Self {
            addr,
            avatar,
            from: Vec::new(),
        }
    }

    /// Whether a datagram from `ip` may drive the avatar.
    #[must_use]
    pub fn allows(&self, ip: IpAddr) -> bool {
        self.from.is_empty() || self.from.iter().any(|c| c.contains(ip))
    }
}

/// One flag value of `--vmc-in`: one or more inputs, comma-separated, each
/// `[ADDR:]PORT=AVATAR` followed by its allow-list, `from=CIDR` and more CIDRs, e.g.
/// `0.0.0.0:39539=avatar,from=192.168.1.0/24,10.0.0.7,39540=bob`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VmcInputs(pub Vec<VmcIn>);

const VMC_IN_FORMS: &str = "[ADDR:]PORT=AVATAR[,from=CIDR,…] (e.g. 39539=avatar, or 0.0.0.0:39539=avatar,from=192.168.1.0/24)";

impl FromStr for VmcInputs {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let mut inputs: Vec<VmcIn> = Vec::new();
        // Whether the previous item was part of an allow-list: a bare CIDR continues it.
        let mut in_list = false;
        for item in s.split(',').map(str::trim) {
            let cidr = |text: &str| {
                text.parse::<Cidr>()
                    .map_err(|e| format!("--vmc-in {s:?}: from={text:?}: {e}"))
            };
            match item.split_once('=') {
                Some(("from", list)) => {
                    let input = inputs.last_mut().ok_or_else(|| {
                        format!("--vmc-in {s:?}: from= must follow an input, {VMC_IN_FORMS}")
                    })?;
                    input.from.push(cidr(list)?);
                    in_list = true;
                }
                Some((addr, avatar)) => {
                    inputs.push(VmcIn::new(
                        listen_addr(addr).map_err(|e| format!("--vmc-in {s:?}: {e}"))?,
                        avatar_id(avatar).map_err(|e| format!("--vmc-in {s:?}: {e}"))?,
                    ));
                    in_list = false;
                }
                None if in_list => {
                    if let Some(input) = inputs.last_mut() {
                        input.from.push(cidr(item)?);
                    }
                }
                None => return Err(format!("{item:?} is not {VMC_IN_FORMS}")),
            }
        }
        Ok(Self(inputs))
    }
}

/// `ADDR:PORT`, or a bare `PORT` on loopback.
fn listen_addr(text: &str) -> Result<SocketAddr, String> {
    if let Ok(port) = text.parse::<u16>() {
        return Ok((Ipv4Addr::LOCALHOST, port).into());
    }
    text.parse().map_err(|e| {
        format!("{text:?} is neither a port nor a socket address (e.g. 0.0.0.0:39539): {e}")
    })
}

impl FromStr for VmcIn {
    type Err = String;

    /// One input, `[ADDR:]PORT=AVATAR[,from=CIDR,…]`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let VmcInputs(mut inputs) = s.parse()?;
        match (inputs.pop(), inputs.is_empty()) {
            (Some(input), true) => Ok(input),
            (None, _) => Err(format!("{s:?} is not {VMC_IN_FORMS}")),
            (Some(_), false) => Err(format!("{s:?} is more than one VMC input")),
        }
    }
}

/// The configuration of one VMC output: `AVATAR=ADDR`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VmcOut {
    /// The avatar whose pose is sent.
    pub avatar: AvatarId,
    /// Where to (VMC's default marionette port is 39539).
    pub addr: SocketAddr,
}

impl FromStr for VmcOut {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (avatar, addr) = s
            .split_once('=')
            .ok_or_else(|| format!("{s:?} is not AVATAR=ADDR (e.g. avatar=127.0.0.1:39539)"))?;
        Ok(Self {
            avatar: avatar_id(avatar)?,
            addr: addr
                .parse()
                .map_err(|e| format!("{addr:?} is not a socket address: {e}"))?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cidrs(list: &[&str]) -> Vec<Cidr> {
        list.iter().map(|c| c.parse().unwrap()).collect()
    }

    #[test]
    fn a_bare_port_binds_to_loopback_and_an_address_where_it_says() {
        let i: VmcIn = "39539=avatar".parse().unwrap();
        assert_eq!(i.addr, "127.0.0.1:39539".parse().unwrap());
        assert!(i.from.is_empty());
        let i: VmcIn = "0.0.0.0:39539=avatar".parse().unwrap();
        assert_eq!(i.addr, "0.0.0.0:39539".parse().unwrap());
        let i: VmcIn = "[::]:39539=avatar".parse().unwrap();
        assert_eq!(i.addr, "[::]:39539".parse().unwrap());
    }

    #[test]
    fn allow_lists_follow_their_input() {
        let VmcInputs(inputs) =
            "0.0.0.0:39539=avatar,from=192.168.1.0/24,10.0.0.7, fd00::/8,39540=bob,from=::1"
                .parse()
                .unwrap();
        assert_eq!(inputs.len(), 2);
        assert_eq!(inputs[0].avatar, AvatarId("avatar".into()));
        assert_eq!(
            inputs[0].from,
            cidrs(&["192.168.1.0/24", "10.0.0.7/32", "fd00::/8"])
        );
        assert_eq!(inputs[1].addr, "127.0.0.1:39540".parse().unwrap());
        assert_eq!(inputs[1].from, cidrs(&["::1"]));
        // `from=` may also repeat.
        let i: VmcIn = "1.2.3.4:5=a,from=10.0.0.0/8,from=127.0.0.1"
            .parse()
            .unwrap();
        assert_eq!(i.from, cidrs(&["10.0.0.0/8", "127.0.0.1"]));
        assert!(i.allows("10.9.8.7".parse().unwrap()));
        assert!(i.allows("127.0.0.1".parse().unwrap()));
        assert!(!i.allows("127.0.0.2".parse().unwrap()));
        assert!(!i.allows("::1".parse().unwrap()));
        assert!(VmcIn::new(i.addr, i.avatar).allows("203.0.113.1".parse().unwrap()));
    }

    #[test]
    fn bad_inputs_say_what_is_wrong() {
        let cases = [
            ("0.0.0.0:39539", "is not [ADDR:]PORT=AVATAR"),
            ("host:1=a", "neither a port nor a socket address"),
            ("70000=a", "neither a port nor a socket address"),
            ("1.2.3.4:5=", "avatar id"),
            ("1.2.3.4:5=a b", "avatar id"),
            ("from=10.0.0.0/8", "from= must follow an input"),
            ("39539=a,from=10.0.0.1/8", "did you mean 10.0.0.0/8"),
            (
                "39539=a,from=10.0.0.0/40",
                "more than the address's 32 bits",
            ),
            ("39539=a,from=lan", "not an IPv4 or IPv6 address"),
            ("39539=a,from=", "not an IPv4 or IPv6 address"),
            // A CIDR outside an allow-list is a typo, not an input.
            ("39539=a,10.0.0.0/8", "is not [ADDR:]PORT=AVATAR"),
        ];
        for (text, says) in cases {
            let e = text.parse::<VmcInputs>().unwrap_err();
            assert!(e.contains(says), "{text}: {e}");
        }
        assert!("39539=a,39540=b".parse::<VmcIn>().is_err());
        assert!("".parse::<VmcIn>().is_err());
    }
}
