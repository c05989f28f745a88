// The one place that makes gRPC channels, and the one that makes server credentials: every client and server of
// FaStage asks here, so how the process's transport is secured is decided once (docs/security.md). The unit test
// stage_channels_are_made_in_one_place fails when another source calls gRPC's own factories.
//
// Plain text (the default) is for loopback only. Mutual TLS: every process holds a certificate of the stage's CA that
// names its identity (scripts/make-test-certs makes a test CA and certificates); servers require and verify the
// client's certificate, clients verify the server's, the files are read again every reload interval (a replaced
// certificate is used from then on without a restart), and every call is authorised by the caller's identity before
// its handler runs (AuthorizeCall): a camera's certificate cannot drive lights.
#pragma once

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace grpc {
class AuthContext;
class Channel;
class ChannelArguments;
class ServerCredentials;
}  // namespace grpc

namespace stage {

struct TransportSecurity {
  enum class Mode { kPlainText, kMutualTls };
  Mode mode = Mode::kPlainText;
  // Mutual TLS: PEM files of the stage's CA, and of this process's certificate (naming its identity) and key.
  std::string ca_file;
  std::string cert_file;
  std::string key_file;
  // How often the three files are read again, s (1..3600): a certificate replaced on disk is used from then on.
  // Replace the certificate and its key together (rename a directory or a symlink), or a reload may pair them wrong.
  int reload_interval_s = 5;

  // InvalidArgument names the field and the file: unreadable, not PEM, a key that is not the certificate's, a
  // certificate the CA did not sign, or one that names no FaStage identity.
  absl::Status Validate() const;
};

// Sets the process's transport security, for every channel and server made after it: call once at start-up, before
// any. Validates first (nothing changes on an error).
absl::Status SetTransportSecurity(const TransportSecurity& security);
TransportSecurity ProcessTransportSecurity();
// "plain text, loopback only", or "mutual TLS as camera/mv-01, CA /etc/fastage/ca.crt": for start-up logs.
std::string DescribeTransportSecurity();

// A channel to `address` ("host:port") with the process's security, or with `security`.
std::shared_ptr<grpc::Channel> MakeChannel(const std::string& address);
std::shared_ptr<grpc::Channel> MakeChannel(const std::string& address, const grpc::ChannelArguments& args);
std::shared_ptr<grpc::Channel> MakeChannel(const std::string& address, const grpc::ChannelArguments& args,
                                           const TransportSecurity& security);

// The credentials a server listens with, with the process's security or with `security` (mutual TLS: calls
// authorised by AuthorizeCall; refusals logged on the "rpc.auth" logger).
std::shared_ptr<grpc::ServerCredentials> MakeServerCredentials();
std::shared_ptr<grpc::ServerCredentials> MakeServerCredentials(const TransportSecurity& security);

// The FaStage identity a certificate names: its URI SAN fastage:<identity>, else its common name. "controller",
// "sim", "camera/<id>", "light/<id>", "worker/<id>", "operator/<name>", "observer/<name>". "" when the peer is not
// authenticated (plain text).
std::string PeerIdentity(const grpc::AuthContext& context);

// Whether `identity` may call `method` ("/stage.v1.LightNode/Arm"); `why` says why not. Light nodes, camera nodes,
// workers and node clocks take calls from the controller (camera nodes' reads also from operators, observers and
// the simulator);
// the stage controller from operators (observers: its Get, List, Watch, Check and Export calls); the simulated world
// from the simulator's processes; the health service from every identity.
bool AuthorizeCall(absl::string_view identity, absl::string_view method, std::string* why);

}  // namespace stage
