//! Self-checksummed JSON documents (the learner's checkpoint manifest, the curriculum snapshot): a
//! `"checksum"` string field holds the CRC-32C of the document's own bytes with that value read as
//! [`UNSEALED`], so a flipped bit or a truncation anywhere in the file is caught before anything in
//! it is trusted.
//!
//! The document is serialised with `"checksum": "00000000"` and then [`seal`]ed, which writes the
//! CRC into those eight characters; [`verify`] reads them back and recomputes. The field is the
//! first key named `checksum` (a quote inside a JSON string is escaped, so the key's pattern cannot
//! occur inside a value).

/// The checksum's value while the document is serialised, and as it is read when the CRC is
/// computed.
pub const UNSEALED: &str = "00000000";

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ChecksumError {
    #[error("it has no checksum field")]
    Missing,
    #[error(
        "its checksum is {computed:08x}, it says {written:?}: the file was changed after it was written"
    )]
    Mismatch { written: String, computed: u32 },
}

/// `doc`, serialised with its checksum field set to [`UNSEALED`], with that value replaced by the
/// document's CRC-32C as 8 lowercase hex digits.
///
/// # Panics
/// When `doc` has no checksum field: a caller's serialisation bug, not input.
pub fn seal(mut doc: Vec<u8>) -> Vec<u8> {
    let at = value_at(&doc).expect("a sealed document has a checksum field");
    let crc = format!("{:08x}", crc(&doc, at));
    doc[at..at + UNSEALED.len()].copy_from_slice(crc.as_bytes());
    doc
}

/// Checks that `doc`'s checksum field holds the CRC-32C of `doc` with that value read as
/// [`UNSEALED`].
pub fn verify(doc: &[u8]) -> Result<(), ChecksumError> {
    let at = value_at(doc).ok_or(ChecksumError::Missing)?;
    let computed = crc(doc, at);
    let written = &doc[at..at + UNSEALED.len()];
    if written == format!("{computed:08x}").as_bytes() {
        Ok(())
    } else {
        Err(ChecksumError::Mismatch {
            written: String::from_utf8_lossy(written).into_owned(),
            computed,
        })
    }
}

/// CRC-32C of `doc` with the 8 bytes at `at` read as [`UNSEALED`].
fn crc(doc: &[u8], at: usize) -> u32 {
    let crc = crc32c::crc32c(&doc[..at]);
    let crc = crc32c::crc32c_append(crc, UNSEALED.as_bytes());
    crc32c::crc32c_append(crc, &doc[at + UNSEALED.len()..])
}

/// Offset of the 8-character value of the first `"checksum": "…"` field.
fn value_at(doc: &[u8]) -> Option<usize> {
    const KEY: &[u8] = b"\"checksum\"";
    let skip_ws = |mut i: usize| {
        while doc.get(i).is_some_and(u8::is_ascii_whitespace) {
            i += 1;
        }
        i
    };
    let mut from = 0;
    while let Some(found) = doc[from..].windows(KEY.len()).position(|w| w == KEY) {
        let key_end = from + found + KEY.len();
        let colon = skip_ws(key_end);
        if doc.get(colon) == Some(&b':') {
            let quote = skip_ws(colon + 1);
            let value = quote + 1;
            if doc.get(quote) == Some(&b'"') && doc.get(value + UNSEALED.len()) == Some(&b'"') {
                return Some(value);
            }
        }
        from = from + found + 1;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sealed_document_verifies_and_any_flipped_bit_is_caught() {
        let doc = br#"{"format": 2, "checksum": "00000000", "state": {"n": 12}}"#.to_vec();
        let sealed = seal(doc.clone());
        assert_ne!(sealed, doc, "the value is written");
        assert_eq!(verify(&sealed), Ok(()));
        for byte in 0..sealed.len() {
            for bit in 0..8 {
                let mut damaged = sealed.clone();
                damaged[byte] ^= 1 << bit;
                assert!(verify(&damaged).is_err(), "byte {byte} bit {bit}");
            }
        }
        for cut in [1, 3, 20] {
            assert!(
                matches!(
                    verify(&sealed[..sealed.len() - cut]),
                    Err(ChecksumError::Mismatch { .. })
                ),
                "truncated by {cut}"
            );
        }
    }

    #[test]
    fn the_crc_is_of_the_bytes_with_the_value_zeroed() {
        // Hand-computed: the value is the CRC-32C of exactly the unsealed bytes.
        let doc = br#"{"checksum":"00000000"}"#.to_vec();
        let expected = format!("{:08x}", crc32c::crc32c(&doc));
        let sealed = seal(doc);
        assert_eq!(&sealed[13..21], expected.as_bytes());
        // Pretty and compact spellings of the field are both found; a value "checksum" is not a key.
        assert_eq!(
            value_at(br#"{"a": "checksum", "checksum" :  "00000000"}"#),
            Some(33)
        );
        assert_eq!(value_at(br#"{"checksum": 12}"#), None);
        assert_eq!(verify(br#"{"format": 1}"#), Err(ChecksumError::Missing));
    }
}
