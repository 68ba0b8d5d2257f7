//! The admin listener's allow list (`admin_allow`): the addresses and networks a
//! connection may come from. Checked on every request, whatever address the listener is
//! bound to, so binding `0.0.0.0` does not open the API to the network by itself.

use std::net::IpAddr;

use ipnet::IpNet;

/// The default `admin_allow`: loopback only.
pub fn default_allow() -> Vec<String> {
    vec!["127.0.0.0/8".into(), "::1/128".into()]
}

/// Parsed `admin_allow`: addresses (`10.0.0.7`) and networks (`10.0.0.0/24`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AllowList(Vec<IpNet>);

impl AllowList {
    /// Parses each entry, an address or a CIDR network; the error names the bad entry.
    pub fn parse(entries: &[String]) -> Result<AllowList, String> {
        entries
            .iter()
            .map(|e| {
                let e = e.trim();
                e.parse::<IpNet>()
                    .or_else(|_| e.parse::<IpAddr>().map(IpNet::from))
                    .map_err(|_| format!("{e:?} is neither an IP address nor a CIDR network"))
            })
            .collect::<Result<Vec<_>, _>>()
            .map(AllowList)
    }

    /// Whether a connection from `ip` is allowed. An IPv4 address mapped into IPv6
    /// (`::ffff:127.0.0.1`, what a dual-stack listener sees) counts as its IPv4 address.
    pub fn allows(&self, ip: IpAddr) -> bool {
        let ip = ip.to_canonical();
        self.0.iter().any(|net| net.contains(&ip))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_networks_and_mapped_addresses() {
        let list = AllowList::parse(&["10.1.2.3".into(), "192.168.0.0/16".into(), "::1".into()]).unwrap();
        assert!(list.allows("10.1.2.3".parse().unwrap()));
        assert!(!list.allows("10.1.2.4".parse().unwrap()));
        assert!(list.allows("192.168.77.1".parse().unwrap()));
        assert!(list.allows("::ffff:10.1.2.3".parse().unwrap()));
        assert!(list.allows("::1".parse().unwrap()));
        let loopback = AllowList::parse(&default_allow()).unwrap();
        assert!(loopback.allows("127.0.0.1".parse().unwrap()));
        assert!(!loopback.allows("10.0.0.1".parse().unwrap()));
        assert!(!loopback.allows("0.0.0.0".parse().unwrap()));
        let err = AllowList::parse(&["10.0.0.0/33".into()]).unwrap_err();
        assert!(err.contains("10.0.0.0/33"), "{err}");
        assert!(AllowList::parse(&["localhost".into()]).is_err());
    }
}
