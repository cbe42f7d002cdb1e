// Round-trips every message of the framediffuser.v1 wire API through its
// binary encoding at realistic sizes (512x512 G-buffers), and checks that no
// message type was added to the proto without being covered here.
#include <cstdint>
#include <functional>
#include <map>
#include <string>

#include <google/protobuf/descriptor.h>
#include <google/protobuf/util/message_differencer.h>
#include <gtest/gtest.h>

#include "framediffuser/v1/image.pb.h"
#include "framediffuser/v1/render_service.grpc.pb.h"
#include "framediffuser/v1/render_service.pb.h"

namespace fd::proto {
namespace {

namespace v1 = ::framediffuser::v1;
using ::google::protobuf::Message;
using ::google::protobuf::util::MessageDifferencer;

constexpr uint32_t kSize = 512;

size_t ElementSize(v1::DType dtype) {
  switch (dtype) {
    case v1::DTYPE_UINT8:
      return 1;
    case v1::DTYPE_FLOAT16:
      return 2;
    case v1::DTYPE_FLOAT32:
      return 4;
    default:
      return 0;
  }
}

// A kSize x kSize image whose bytes follow a deterministic pattern, so a
// corrupted round trip cannot compare equal by accident.
v1::Image MakeImage(uint32_t channels, v1::DType dtype, uint8_t salt) {
  v1::Image image;
  image.set_width(kSize);
  image.set_height(kSize);
  image.set_channels(channels);
  image.set_dtype(dtype);
  image.set_compression(v1::COMPRESSION_NONE);
  std::string data(size_t{kSize} * kSize * channels * ElementSize(dtype), '\0');
  for (size_t i = 0; i < data.size(); ++i) {
    data[i] = static_cast<char>((i * 31 + salt) & 0xff);
  }
  image.set_data(std::move(data));
  return image;
}

v1::GBuffer MakeGBuffer() {
  v1::GBuffer g;
  *g.mutable_basecolor() = MakeImage(3, v1::DTYPE_UINT8, 1);
  *g.mutable_normals() = MakeImage(3, v1::DTYPE_FLOAT16, 2);
  *g.mutable_depth() = MakeImage(1, v1::DTYPE_FLOAT32, 3);
  *g.mutable_roughness() = MakeImage(1, v1::DTYPE_UINT8, 4);
  *g.mutable_metallic() = MakeImage(1, v1::DTYPE_UINT8, 5);
  return g;
}

v1::Environment MakeEnvironment() {
  v1::Environment env;
  env.set_name("downtown_west");
  env.set_description("FrameDiffuser trained on Downtown West");
  env.set_prompt("a photorealistic city street, daylight");
  env.set_native_width(512);
  env.set_native_height(512);
  env.set_default_steps(10);
  env.set_max_steps(50);
  env.set_default_scheduler(v1::SCHEDULER_UNIPC);
  env.set_default_sky_mode(v1::SKY_MODE_PREVIOUS_OUTPUT);
  env.set_readiness(v1::READINESS_READY);
  env.set_min_size(64);
  env.set_max_size(1024);
  return env;
}

v1::OpenSession MakeOpen() {
  v1::OpenSession open;
  open.set_environment("downtown_west");
  open.set_width(kSize);
  open.set_height(kSize);
  open.set_seed(0xfeedfacecafebeefULL);
  open.set_steps(10);
  open.set_scheduler(v1::SCHEDULER_DPM_SOLVER_PP_2M);
  open.set_sky_mode(v1::SKY_MODE_CLIENT_IMAGE);
  *open.mutable_keyframe() = MakeImage(3, v1::DTYPE_UINT8, 6);
  *open.mutable_keyframe_basecolor() = MakeImage(3, v1::DTYPE_UINT8, 7);
  open.set_output_dtype(v1::DTYPE_FLOAT16);
  open.set_output_compression(v1::COMPRESSION_ZSTD);
  open.set_max_frames_in_flight(2);
  return open;
}

v1::SessionSettings MakeSettings() {
  v1::SessionSettings s;
  s.set_environment("downtown_west");
  s.set_width(kSize);
  s.set_height(kSize);
  s.set_seed(42);
  s.set_steps(10);
  s.set_scheduler(v1::SCHEDULER_UNIPC);
  s.set_sky_mode(v1::SKY_MODE_OFF);
  s.set_output_dtype(v1::DTYPE_UINT8);
  s.set_output_compression(v1::COMPRESSION_NONE);
  s.set_max_frames_in_flight(2);
  s.set_started_from_keyframe(true);
  return s;
}

v1::FrameInput MakeFrame() {
  v1::FrameInput frame;
  frame.set_frame_index(1234);
  *frame.mutable_gbuffer() = MakeGBuffer();
  *frame.mutable_sky() = MakeImage(3, v1::DTYPE_UINT8, 8);
  *frame.mutable_keyframe() = MakeImage(3, v1::DTYPE_FLOAT32, 9);
  *frame.mutable_keyframe_basecolor() = MakeImage(3, v1::DTYPE_UINT8, 10);
  return frame;
}

v1::StageTimings MakeTimings() {
  v1::StageTimings t;
  t.set_queue_ms(1.25);
  t.set_encode_ms(3.5);
  t.set_denoise_ms(80.0);
  t.set_decode_ms(12.0);
  t.set_total_ms(97.0);
  t.set_batch_size(8);
  return t;
}

v1::RenderedFrame MakeRendered() {
  v1::RenderedFrame r;
  r.set_frame_index(1234);
  *r.mutable_image() = MakeImage(3, v1::DTYPE_UINT8, 11);
  *r.mutable_timings() = MakeTimings();
  return r;
}

v1::SessionOpened MakeOpened() {
  v1::SessionOpened o;
  o.set_session_id("0123456789abcdef0123456789abcdef");
  o.set_resume_token("c2VjcmV0LXJlc3VtZS10b2tlbi0xMjg");
  *o.mutable_settings() = MakeSettings();
  o.set_resumed(true);
  o.set_last_frame_index(0);  // explicit presence: 0 is a real value here
  return o;
}

// One builder per message type of the package, keyed by full name.
std::map<std::string, std::function<void(Message*)>> Builders() {
  std::map<std::string, std::function<void(Message*)>> b;
  auto add = [&b](auto make) {
    using M = decltype(make());
    b[M::descriptor()->full_name()] = [make](Message* m) { m->CopyFrom(make()); };
  };
  add([] { return MakeImage(3, v1::DTYPE_UINT8, 0); });
  add(MakeEnvironment);
  add([] { return v1::ListEnvironmentsRequest(); });
  add([] {
    v1::ListEnvironmentsResponse r;
    *r.add_environments() = MakeEnvironment();
    *r.add_environments() = MakeEnvironment();
    r.mutable_environments(1)->set_name("hillside");
    r.mutable_environments(1)->set_readiness(v1::READINESS_FAILED);
    r.mutable_environments(1)->set_readiness_detail("unet/config.json: missing");
    return r;
  });
  add([] {
    v1::RenderRequest r;
    *r.mutable_frame() = MakeFrame();
    return r;
  });
  add(MakeOpen);
  add([] {
    v1::ResumeSession r;
    r.set_session_id("0123456789abcdef0123456789abcdef");
    r.set_resume_token("c2VjcmV0");
    return r;
  });
  add(MakeGBuffer);
  add(MakeFrame);
  add([] {
    v1::RenderResponse r;
    *r.mutable_frame() = MakeRendered();
    return r;
  });
  add(MakeSettings);
  add(MakeOpened);
  add(MakeTimings);
  add(MakeRendered);
  add([] {
    v1::FrameError e;
    e.set_frame_index(7);
    e.set_code(3);
    e.set_message("frame.gbuffer.depth.channels: expected 1, got 3");
    return e;
  });
  add([] {
    v1::SessionNotice n;
    n.set_reason(v1::SessionNotice::REASON_DRAINING);
    n.set_message("server shutting down");
    return n;
  });
  return b;
}

void ExpectRoundTrip(const Message& original) {
  std::string wire;
  ASSERT_TRUE(original.SerializeToString(&wire)) << original.GetTypeName();
  std::unique_ptr<Message> parsed(original.New());
  ASSERT_TRUE(parsed->ParseFromString(wire)) << original.GetTypeName();
  std::string diff;
  MessageDifferencer differencer;
  differencer.ReportDifferencesToString(&diff);
  EXPECT_TRUE(differencer.Compare(original, *parsed)) << original.GetTypeName() << ": " << diff;
  EXPECT_EQ(parsed->ByteSizeLong(), wire.size());
}

TEST(ProtoRoundTripTest, EveryMessageTypeOfThePackageHasABuilder) {
  const auto builders = Builders();
  const auto* pool = google::protobuf::DescriptorPool::generated_pool();
  for (const char* file : {"framediffuser/v1/image.proto", "framediffuser/v1/render_service.proto"}) {
    const auto* fd = pool->FindFileByName(file);
    ASSERT_NE(fd, nullptr) << file;
    for (int i = 0; i < fd->message_type_count(); ++i) {
      EXPECT_TRUE(builders.count(fd->message_type(i)->full_name()))
          << fd->message_type(i)->full_name() << " has no round-trip builder";
    }
  }
}

TEST(ProtoRoundTripTest, EveryMessageTypeSurvivesSerializeAndParse) {
  const auto* pool = google::protobuf::DescriptorPool::generated_pool();
  auto* factory = google::protobuf::MessageFactory::generated_factory();
  for (const auto& [name, build] : Builders()) {
    SCOPED_TRACE(name);
    const auto* desc = pool->FindMessageTypeByName(name);
    ASSERT_NE(desc, nullptr);
    std::unique_ptr<Message> msg(factory->GetPrototype(desc)->New());
    build(msg.get());
    ExpectRoundTrip(*msg);
  }
}

TEST(ProtoRoundTripTest, EveryOneofCaseOfTheStreamMessagesRoundTrips) {
  v1::RenderRequest open_req;
  *open_req.mutable_open() = MakeOpen();
  v1::RenderRequest resume_req;
  resume_req.mutable_resume()->set_session_id("ab");
  v1::RenderResponse opened;
  *opened.mutable_opened() = MakeOpened();
  v1::RenderResponse err;
  err.mutable_frame_error()->set_frame_index(3);
  v1::RenderResponse notice;
  notice.mutable_notice()->set_reason(v1::SessionNotice::REASON_EVICTED);
  for (const Message* m :
       std::initializer_list<const Message*>{&open_req, &resume_req, &opened, &err, &notice}) {
    ExpectRoundTrip(*m);
  }
}

TEST(ProtoRoundTripTest, RealisticFrameSizesFitTheServerMessageLimit) {
  // A 512x512 uint8 G-buffer frame with sky is ~2 MiB, well under gRPC's
  // default 4 MiB limit; float32 planes need the server's raised limit.
  v1::RenderRequest r;
  *r.mutable_frame()->mutable_gbuffer() = MakeGBuffer();
  const size_t bytes = r.ByteSizeLong();
  EXPECT_GT(bytes, size_t{kSize} * kSize * 9);  // every plane is really there
  EXPECT_LT(bytes, size_t{16} << 20);
}

TEST(ProtoRoundTripTest, OptionalLastFrameIndexKeepsPresenceOfZero) {
  v1::SessionOpened with_zero;
  with_zero.set_last_frame_index(0);
  v1::SessionOpened parsed;
  ASSERT_TRUE(parsed.ParseFromString(with_zero.SerializeAsString()));
  EXPECT_TRUE(parsed.has_last_frame_index());
  v1::SessionOpened without;
  ASSERT_TRUE(parsed.ParseFromString(without.SerializeAsString()));
  EXPECT_FALSE(parsed.has_last_frame_index());
}

TEST(ProtoRoundTripTest, ServiceHasTheDocumentedMethods) {
  const auto* svc = v1::FrameDiffuser::service_full_name();
  EXPECT_STREQ(svc, "framediffuser.v1.FrameDiffuser");
  const auto* desc = google::protobuf::DescriptorPool::generated_pool()->FindServiceByName(svc);
  ASSERT_NE(desc, nullptr);
  const auto* render = desc->FindMethodByName("Render");
  ASSERT_NE(render, nullptr);
  EXPECT_TRUE(render->client_streaming());
  EXPECT_TRUE(render->server_streaming());
  const auto* list = desc->FindMethodByName("ListEnvironments");
  ASSERT_NE(list, nullptr);
  EXPECT_FALSE(list->client_streaming());
  EXPECT_FALSE(list->server_streaming());
}

}  // namespace
}  // namespace fd::proto
