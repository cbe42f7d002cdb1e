// The byte layout of a state blob (state_blob.h), version 1.
//
// All integers little-endian, fields back to back, no padding:
//   magic                 4 B   "FDSS"
//   version               u16   kStateBlobVersion
//   flags                 u16   reserved, 0
//   environment_length    u16   <= kMaxEnvironmentNameBytes
//   environment           bytes (UTF-8, environment_length bytes)
//   width, height         u32, u32
//   seed                  u64
//   steps                 u32
//   scheduler             u8    SchedulerKind
//   sky_mode              u8    SkyMode
//   output_dtype          u8    OutputDType
//   output_compression    u8    OutputCompression
//   max_frames_in_flight  u32
//   start_mode            u8    StartMode
//   frame_counter         u64
//   has_last_frame_index  u8    0 or 1
//   last_frame_index      u64   (0 when absent)
//   has_previous_frame    u8    0 or 1
//   has_previous_basecolor u8   0 or 1
//   pixel_bytes           u64   uncompressed: (has_previous_frame +
//                               has_previous_basecolor) * width*height*3
//   compressed_bytes      u64   0 when pixel_bytes is 0
//   pixels                bytes one zstd frame (with content size and
//                               checksum) of previous_frame then
//                               previous_basecolor, uint8 HWC RGB each
//   checksum              u64   FNV-1a 64 of every byte before it
// A new version may add fields; readers reject versions they do not know.
#ifndef FD_SESSION_STATE_BLOB_FORMAT_H_
#define FD_SESSION_STATE_BLOB_FORMAT_H_

#include <cstddef>
#include <cstdint>
#include <string_view>

namespace fd::session {

inline constexpr std::string_view kStateBlobMagic = "FDSS";
inline constexpr uint16_t kStateBlobVersion = 1;
inline constexpr size_t kMaxEnvironmentNameBytes = 256;
// Bytes of the trailing checksum.
inline constexpr size_t kStateBlobChecksumBytes = 8;

// FNV-1a, 64 bit. Detects accidental corruption (not an authenticator: a
// blob is trusted as much as whoever hands it over).
constexpr uint64_t StateBlobChecksum(std::string_view bytes) {
  uint64_t hash = 0xcbf29ce484222325ULL;
  for (char c : bytes) {
    hash ^= static_cast<uint8_t>(c);
    hash *= 0x100000001b3ULL;
  }
  return hash;
}

}  // namespace fd::session

#endif  // FD_SESSION_STATE_BLOB_FORMAT_H_
