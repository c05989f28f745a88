// The transport security a rig sets for a process (rig.proto's SecurityConfig; docs/security.md).
#pragma once

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "stage/common/rig.h"
#include "stage/common/rpc_channel.h"

namespace stage {

// Plain text, or mutual TLS with the CA and `identity`'s certificate and key from security.cert_dir (the identity's
// "/" as "-": camera/mv-01 -> camera-mv-01.crt and .key), relative paths against the rig's folder.
TransportSecurity RigTransportSecurity(const LoadedRig& rig, absl::string_view identity);

// RigTransportSecurity, checked and set as the process's (SetTransportSecurity); mutual TLS is said in the log
// ("transport: mutual TLS as camera/mv-01, CA ..."), plain text where a server starts. InvalidArgument names the
// file and the field.
absl::Status UseRigTransportSecurity(const LoadedRig& rig, absl::string_view identity);

}  // namespace stage
