//! Whether an executable is statically linked: it is when its ELF program headers name no
//! interpreter (`PT_INTERP`, the dynamic loader). A static PIE still has a `PT_DYNAMIC` (its
//! own relocations), so that one says nothing.

use std::fs::File;
use std::io;
use std::os::unix::fs::FileExt;
use std::path::Path;

const PT_INTERP: u32 = 3;
/// The ELF64 header's size, and where its fields are.
const EHDR_LEN: usize = 64;
const E_PHOFF: usize = 32;
const E_PHENTSIZE: usize = 54;
const E_PHNUM: usize = 56;

/// Whether the executable at `path` is linked dynamically (asks for a loader).
pub fn is_dynamically_linked(path: &Path) -> io::Result<bool> {
    let file = File::open(path)?;
    let mut ehdr = [0u8; EHDR_LEN];
    file.read_exact_at(&mut ehdr, 0)?;
    let (phoff, phentsize, phnum) = program_headers(&ehdr).map_err(invalid)?;
    // Within the file, before anything is allocated for them: a damaged header may name up to
    // 4 GiB of them.
    let len = (phentsize * phnum) as u64;
    let size = file.metadata()?.len();
    if phoff.checked_add(len).is_none_or(|end| end > size) {
        return Err(invalid("program headers past the end of the file"));
    }
    let mut phdrs = vec![0u8; len as usize];
    file.read_exact_at(&mut phdrs, phoff)?;
    Ok(names_interpreter(&phdrs, phentsize))
}

fn invalid(why: &'static str) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, why)
}

/// Where the program headers of the ELF64 little-endian header `ehdr` are: (offset, entry
/// size, count).
fn program_headers(ehdr: &[u8; EHDR_LEN]) -> Result<(u64, usize, usize), &'static str> {
    if ehdr[..4] != *b"\x7fELF" {
        return Err("not an ELF file");
    }
    if ehdr[4] != 2 || ehdr[5] != 1 {
        return Err("not a 64-bit little-endian ELF file");
    }
    let u16_at = |o: usize| u16::from_le_bytes([ehdr[o], ehdr[o + 1]]) as usize;
    let phoff = u64::from_le_bytes(ehdr[E_PHOFF..E_PHOFF + 8].try_into().expect("8 bytes"));
    let (phentsize, phnum) = (u16_at(E_PHENTSIZE), u16_at(E_PHNUM));
    if phentsize < 4 {
        return Err("program header entries too small");
    }
    Ok((phoff, phentsize, phnum))
}

/// Whether one of the program headers in `phdrs` (entries of `phentsize` bytes) is `PT_INTERP`.
fn names_interpreter(phdrs: &[u8], phentsize: usize) -> bool {
    phdrs
        .chunks_exact(phentsize)
        .any(|ph| u32::from_le_bytes([ph[0], ph[1], ph[2], ph[3]]) == PT_INTERP)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// An ELF64 header with `types` as its program headers (56 bytes each, right after it):
    /// `[3]` (`PT_INTERP`) reads as dynamically linked, `[1]` (`PT_LOAD`) as static.
    pub(crate) fn elf(types: &[u32]) -> Vec<u8> {
        let mut f = vec![0u8; EHDR_LEN];
        f[..4].copy_from_slice(b"\x7fELF");
        f[4] = 2;
        f[5] = 1;
        f[E_PHOFF..E_PHOFF + 8].copy_from_slice(&(EHDR_LEN as u64).to_le_bytes());
        f[E_PHENTSIZE..E_PHENTSIZE + 2].copy_from_slice(&56u16.to_le_bytes());
        f[E_PHNUM..E_PHNUM + 2].copy_from_slice(&(types.len() as u16).to_le_bytes());
        for t in types {
            let mut ph = [0u8; 56];
            ph[..4].copy_from_slice(&t.to_le_bytes());
            f.extend_from_slice(&ph);
        }
        f
    }

    fn check(bytes: &[u8]) -> io::Result<bool> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("exe");
        std::fs::write(&path, bytes).unwrap();
        is_dynamically_linked(&path)
    }

    #[test]
    fn an_interpreter_makes_an_executable_dynamic() {
        // PT_PHDR, PT_INTERP, PT_LOAD, PT_DYNAMIC: a dynamic PIE.
        assert!(check(&elf(&[6, 3, 1, 2])).unwrap());
        // PT_LOAD, PT_DYNAMIC, PT_TLS: a static PIE.
        assert!(!check(&elf(&[1, 2, 7])).unwrap());
    }

    #[test]
    fn what_is_no_elf_executable_is_an_error() {
        assert!(check(b"#!/bin/sh\necho hello, this is a shell script not an ELF\n").is_err());
        let mut be = elf(&[1]);
        be[5] = 2;
        assert!(check(&be).is_err());
        // Headers said to lie past the end of the file.
        let mut short = elf(&[1, 3]);
        short.truncate(EHDR_LEN + 20);
        assert!(check(&short).is_err());
        // Or far past it (65,535 of 65,535 bytes each).
        let mut huge = elf(&[1]);
        huge[E_PHENTSIZE..E_PHENTSIZE + 2].copy_from_slice(&u16::MAX.to_le_bytes());
        huge[E_PHNUM..E_PHNUM + 2].copy_from_slice(&u16::MAX.to_le_bytes());
        assert!(check(&huge).is_err());
    }
}
