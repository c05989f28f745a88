// NodeClock: the exchange through a real server, and pmc's output as linuxptp 3.1 prints it.
#include "stage/common/node_clock.h"

#include <grpcpp/grpcpp.h>

#include "gtest/gtest.h"
#include "stage/common/rpc_channel.h"
#include "stage/common/rpc_server.h"

namespace stage {
namespace {

// Captured from linuxptp 3.1.1's pmc against a ptp4l slave (software timestamping, veth in a network namespace).
constexpr const char* kPmcSlave = R"(sending: GET TIME_STATUS_NP
sending: GET PORT_DATA_SET
sending: GET CURRENT_DATA_SET
	e6c9db.fffe.cd6a0c-0 seq 0 RESPONSE MANAGEMENT TIME_STATUS_NP 
		master_offset              -1933
		ingress_time               1795420255732880332
		cumulativeScaledRateOffset +0.000000000
		scaledLastGmPhaseChange    0
		gmTimeBaseIndicator        0
		lastGmPhaseChange          0x0000'0000000000000000.0000
		gmPresent                  true
		gmIdentity                 62c86a.fffe.54ddc3
	e6c9db.fffe.cd6a0c-1 seq 1 RESPONSE MANAGEMENT PORT_DATA_SET 
		portIdentity            e6c9db.fffe.cd6a0c-1
		portState               UNCALIBRATED
		logMinDelayReqInterval  0
		peerMeanPathDelay       0
		logAnnounceInterval     1
		announceReceiptTimeout  3
		logSyncInterval         0
		delayMechanism          1
		logMinPdelayReqInterval 0
		versionNumber           2
	e6c9db.fffe.cd6a0c-0 seq 2 RESPONSE MANAGEMENT CURRENT_DATA_SET 
		stepsRemoved     1
		offsetFromMaster -1933.0
		meanPathDelay    2864.0
)";

TEST(PmcOutputTest, ReadsStateOffsetAndGrandmaster) {
  v1::PtpStatus s = ParsePmcOutput(kPmcSlave);
  EXPECT_EQ(s.source(), "linuxptp");
  EXPECT_EQ(s.port_state(), "UNCALIBRATED");
  EXPECT_EQ(s.master_offset_ns(), -1933);
  EXPECT_EQ(s.mean_path_delay_ns(), 2864);
  EXPECT_EQ(s.grandmaster_id(), "62c86a.fffe.54ddc3");
  EXPECT_TRUE(s.grandmaster_present());
  EXPECT_EQ(s.steps_removed(), 1);
  EXPECT_TRUE(s.error().empty());
}

TEST(PmcOutputTest, NoAnswerIsAnError) {
  v1::PtpStatus s = ParsePmcOutput("sending: GET TIME_STATUS_NP\n");
  EXPECT_FALSE(s.error().empty());
}

TEST(PtpProbeTest, ASocketNobodyServesGivesAnErrorNotAHang) {
  LinuxPtpProbe probe("/nonexistent/ptp4l");
  v1::PtpStatus s = probe.ReadNow();
  EXPECT_EQ(s.source(), "linuxptp");
  EXPECT_FALSE(s.error().empty());
  EXPECT_TRUE(MakePtpProbe("none") == nullptr);
}

class FixedPtp final : public PtpProbe {
 public:
  v1::PtpStatus Latest() const override {
    v1::PtpStatus s;
    s.set_source("linuxptp");
    s.set_port_state("SLAVE");
    return s;
  }
};

TEST(NodeClockServiceTest, StampsArrivalAndDepartureOnTheNodeClock) {
  SimClock clock(7'000'000'000);
  FixedPtp ptp;
  NodeClockService service(&clock, "CLOCK_REALTIME", &ptp);
  auto server = RpcServer::Start({.listen = "127.0.0.1:0"}, {&service});
  ASSERT_TRUE(server.ok());
  auto stub = v1::NodeClock::NewStub(MakeChannel((*server)->address()));
  grpc::ClientContext context;
  v1::SyncRequest request;
  request.set_t1_ns(123);
  v1::SyncResponse response;
  ASSERT_TRUE(stub->Sync(&context, request, &response).ok());
  EXPECT_EQ(response.t1_ns(), 123);
  EXPECT_EQ(response.t2_ns(), 7'000'000'000);
  EXPECT_EQ(response.t3_ns(), 7'000'000'000);
  EXPECT_EQ(response.clock(), "CLOCK_REALTIME");
  EXPECT_EQ(response.ptp().port_state(), "SLAVE");
}

}  // namespace
}  // namespace stage
